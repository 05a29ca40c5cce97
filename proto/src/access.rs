//! What every SAVER server and client agrees on beyond the messages: the shared token
//! (sent as `authorization: Bearer <token>` on every call and checked by the servers),
//! TLS (rustls) when a server has a certificate, and the HTTP/2 settings of both ends
//! (keepalive, so that a cut link is noticed).

use crate::admit::{Admitted, Guarded, AUTH_GRACE};
use std::sync::Arc;
use std::time::Duration;
use tonic::metadata::{Ascii, MetadataValue};
use tonic::service::Interceptor;
pub use tonic::transport::{Certificate, ClientTlsConfig, Identity, ServerTlsConfig};
use tonic::transport::{Endpoint, Server};
use tonic::{Request, Status};

/// Metadata key that carries the token.
pub const AUTH_KEY: &str = "authorization";

/// How often each end pings an idle connection, and how long it waits for the answer
/// before it drops the connection (a cut link is noticed within their sum).
pub const KEEPALIVE_INTERVAL: Duration = Duration::from_secs(4);
/// See [`KEEPALIVE_INTERVAL`].
pub const KEEPALIVE_TIMEOUT: Duration = Duration::from_secs(8);

/// Why a token cannot be used.
#[derive(Debug, thiserror::Error)]
#[error("the token {0}")]
pub struct TokenError(&'static str);

/// Checks a token's form: 1 to 4096 visible ASCII characters (it travels in a header).
pub fn validate_token(token: &str) -> Result<(), TokenError> {
    if token.is_empty() {
        return Err(TokenError("is empty"));
    }
    if token.len() > 4096 {
        return Err(TokenError("is longer than 4096 bytes"));
    }
    if !token.bytes().all(|b| b.is_ascii_graphic()) {
        return Err(TokenError(
            "must be visible ASCII characters (no spaces or control characters)",
        ));
    }
    Ok(())
}

/// Server side: refuses every call that does not carry the expected token with
/// UNAUTHENTICATED. With no token configured it lets everything through. A call that
/// passes admits its connection ([`crate::admit`]).
#[derive(Clone, Default)]
pub struct CheckToken {
    /// `Bearer <token>` as bytes.
    expected: Option<Arc<[u8]>>,
    /// Connections whose call passed.
    admitted: Admitted,
}

impl CheckToken {
    /// A check for `token` (`None`: no check).
    pub fn new(token: Option<&str>) -> Result<Self, TokenError> {
        if let Some(t) = token {
            validate_token(t)?;
        }
        Ok(Self {
            expected: token.map(|t| format!("Bearer {t}").into_bytes().into()),
            admitted: Admitted::default(),
        })
    }
}

/// Equality in time independent of where the first difference is.
pub fn same_bytes(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

impl Interceptor for CheckToken {
    fn call(&mut self, req: Request<()>) -> Result<Request<()>, Status> {
        if let Some(expected) = &self.expected {
            match req.metadata().get(AUTH_KEY) {
                None => {
                    return Err(Status::unauthenticated(
                        "this server needs a token: pass --token, SAVER_TOKEN or --token-file",
                    ))
                }
                Some(v) if same_bytes(v.as_bytes(), expected) => {}
                Some(_) => return Err(Status::unauthenticated("wrong token")),
            }
        }
        if let Some(peer) = req.remote_addr() {
            self.admitted.admit(peer);
        }
        Ok(req)
    }
}

/// Client side: adds the token to every call.
#[derive(Clone, Default)]
pub struct AddToken {
    value: Option<MetadataValue<Ascii>>,
}

impl AddToken {
    /// Sends `token` (`None`: sends nothing).
    pub fn new(token: Option<&str>) -> Result<Self, TokenError> {
        let value = match token {
            None => None,
            Some(t) => {
                validate_token(t)?;
                Some(
                    format!("Bearer {t}")
                        .parse()
                        .map_err(|_| TokenError("cannot be sent as a header"))?,
                )
            }
        };
        Ok(Self { value })
    }
}

impl Interceptor for AddToken {
    fn call(&mut self, mut req: Request<()>) -> Result<Request<()>, Status> {
        if let Some(v) = &self.value {
            req.metadata_mut().insert(AUTH_KEY, v.clone());
        }
        Ok(req)
    }
}

/// A server's access settings: the token it requires and its TLS identity.
#[derive(Clone, Default)]
pub struct Access {
    /// Checks the token.
    pub check: CheckToken,
    /// Serve TLS with this certificate and key (`None`: plain HTTP/2).
    pub tls: Option<ServerTlsConfig>,
}

impl Access {
    /// Only a token check, no TLS.
    pub fn token(check: CheckToken) -> Self {
        Self { check, tls: None }
    }

    /// The connections a server accepts on `listener`: Nagle's algorithm off, and
    /// each closed unless a call passes the token check within
    /// [`crate::admit::AUTH_GRACE`].
    ///
    /// `Server::tcp_nodelay` applies only to addresses the server binds itself; a
    /// server fed a listener (every SAVER server: they bind first, to report the
    /// port) must set it per accepted socket, here. Without it a pushed weights
    /// message waited for the actor's delayed ACK: 16 sync actor processes ran ~38 ms
    /// rounds on loopback.
    pub fn incoming(
        &self,
        listener: tokio::net::TcpListener,
    ) -> impl tokio_stream::Stream<Item = std::io::Result<Guarded>> {
        use tokio_stream::StreamExt;
        let admitted = self.check.admitted.clone();
        tonic::transport::server::TcpIncoming::from(listener)
            .with_nodelay(Some(true))
            .map(move |s| s.map(|s| Guarded::new(s, admitted.clone(), AUTH_GRACE)))
    }

    /// The transport of a server with these settings (see [`server`]).
    pub fn server(&self) -> Result<Server, tonic::transport::Error> {
        match &self.tls {
            Some(tls) => server().tls_config(tls.clone()),
            None => Ok(server()),
        }
    }
}

/// What a client sends and trusts: the token, and for `https://` URLs the CA that
/// signed the server's certificate.
#[derive(Clone, Default)]
pub struct ClientAccess {
    /// Adds the token.
    pub token: AddToken,
    /// TLS settings (the CA) for https URLs.
    pub tls: Option<ClientTlsConfig>,
}

/// Why a client cannot reach a server.
#[derive(Debug, thiserror::Error)]
pub enum ConnectError {
    /// The URL or TLS settings are unusable.
    #[error("{0}")]
    Setup(String),
    /// The transport failed.
    #[error(transparent)]
    Transport(#[from] tonic::transport::Error),
}

impl ClientAccess {
    /// An endpoint for `url` (see [`endpoint`]) with TLS for `https://`.
    pub fn endpoint(&self, url: &str) -> Result<Endpoint, ConnectError> {
        let e = endpoint(url)?;
        match (&self.tls, url.starts_with("https://")) {
            (Some(tls), true) => Ok(e.tls_config(tls.clone())?),
            (None, true) => Err(ConnectError::Setup(format!(
                "{url} is https: give the CA that signed its certificate (--tls-ca)"
            ))),
            (Some(_), false) => Err(ConnectError::Setup(format!(
                "a CA was given but {url} is not https://"
            ))),
            (None, false) => Ok(e),
        }
    }
}

/// A client endpoint for `url` with the settings of every SAVER client: no Nagle
/// delay, windows that hold a weights message, keepalive pings while idle.
pub fn endpoint(url: &str) -> Result<Endpoint, tonic::transport::Error> {
    Ok(Endpoint::from_shared(url.to_string())?
        .tcp_nodelay(true)
        .connect_timeout(Duration::from_secs(10))
        .initial_stream_window_size(Some(4 << 20))
        .initial_connection_window_size(Some(8 << 20))
        .http2_keep_alive_interval(KEEPALIVE_INTERVAL)
        .keep_alive_timeout(KEEPALIVE_TIMEOUT)
        .keep_alive_while_idle(true))
}

/// The transport settings every SAVER server uses (see [`Access::server`] for TLS):
/// small receive windows (64 KiB per stream, 1 MiB per connection), so an actor cannot
/// park thousands of rollouts in flight that are stale when they arrive (the clients'
/// windows, which carry weights the other way, are large); keepalive pings (a peer
/// behind a cut link is dropped, so its streams end and a sync round stops waiting for
/// it). No Nagle delay comes from [`Access::incoming`]: every SAVER server is fed a listener,
/// for which `Server::tcp_nodelay` does nothing.
pub fn server() -> tonic::transport::Server {
    tonic::transport::Server::builder()
        .initial_stream_window_size(Some(64 << 10))
        .initial_connection_window_size(Some(1 << 20))
        .http2_keepalive_interval(Some(KEEPALIVE_INTERVAL))
        .http2_keepalive_timeout(Some(KEEPALIVE_TIMEOUT))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn with_header(v: Option<&str>) -> Request<()> {
        let mut r = Request::new(());
        if let Some(v) = v {
            r.metadata_mut().insert(AUTH_KEY, v.parse().unwrap());
        }
        r
    }

    #[test]
    fn token_check_lets_only_the_right_token_through() {
        let mut check = CheckToken::new(Some("s3cret")).unwrap();
        assert!(check.call(with_header(Some("Bearer s3cret"))).is_ok());
        for bad in [
            None,
            Some("Bearer s3cre"),
            Some("Bearer s3cret2"),
            Some("s3cret"),
        ] {
            let e = check.call(with_header(bad)).unwrap_err();
            assert_eq!(e.code(), tonic::Code::Unauthenticated, "{bad:?}");
        }
        // The client interceptor writes exactly what the check expects.
        let sent = AddToken::new(Some("s3cret"))
            .unwrap()
            .call(Request::new(()));
        assert!(check.call(sent.unwrap()).is_ok());
        // No token configured: everything passes.
        assert!(CheckToken::default().call(with_header(None)).is_ok());
    }

    #[test]
    fn malformed_tokens_are_refused() {
        for bad in ["", "two words", "tab\there", "é"] {
            assert!(validate_token(bad).is_err(), "{bad:?}");
        }
        assert!(validate_token(&"x".repeat(4097)).is_err());
        assert!(validate_token("a-Z_0.9~!").is_ok());
    }
}

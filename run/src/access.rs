//! Who may talk to a server: the shared token (flag, SAVER_TOKEN or a file) that every
//! server checks and every client sends, TLS (a certificate and key for servers, the CA
//! for clients), and the refusal to serve a non-loopback address with neither token
//! nor TLS unless the user says `--insecure`.

use anyhow::{bail, Context, Result};
use clap::Args;
use saver_proto::access::{Certificate, ClientTlsConfig, Identity, ServerTlsConfig};
use saver_proto::{Access, AddToken, CheckToken, ClientAccess};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};

fn read(path: &Path, what: &str) -> Result<Vec<u8>> {
    std::fs::read(path).with_context(|| format!("reading the {what} {}", path.display()))
}

/// Client TLS that trusts the CA certificate (PEM) in `path`.
pub fn client_tls(path: &Path) -> Result<ClientTlsConfig> {
    let pem = read(path, "CA certificate")?;
    Ok(ClientTlsConfig::new().ca_certificate(Certificate::from_pem(pem)))
}

/// The shared token, for servers and clients alike.
#[derive(Args, Clone, Debug, Default)]
pub struct TokenArgs {
    /// Shared secret every call carries (servers refuse calls without it).
    #[arg(long, env = "SAVER_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// Read the token from this file (its first line).
    #[arg(long, value_name = "FILE", conflicts_with = "token")]
    pub token_file: Option<PathBuf>,
}

/// Warns when a token file can be read by other users of the machine.
fn warn_if_readable_by_others(path: &std::path::Path) {
    use std::os::unix::fs::PermissionsExt;
    if let Ok(m) = std::fs::metadata(path) {
        let mode = m.permissions().mode();
        if mode & 0o044 != 0 {
            tracing::warn!(
                "the token file {} is readable by other users (mode {:o}); \
                 `chmod 600 {}` keeps the token yours",
                path.display(),
                mode & 0o777,
                path.display()
            );
        }
    }
}

impl TokenArgs {
    /// The token, if one was given.
    pub fn token(&self) -> Result<Option<String>> {
        let token = match (&self.token, &self.token_file) {
            (Some(t), _) => Some(t.clone()),
            (None, Some(path)) => {
                let text = std::fs::read_to_string(path)
                    .with_context(|| format!("reading the token file {}", path.display()))?;
                warn_if_readable_by_others(path);
                Some(text.lines().next().unwrap_or("").trim().to_string())
            }
            (None, None) => None,
        };
        if let Some(t) = &token {
            saver_proto::access::validate_token(t)?;
        }
        Ok(token)
    }

    /// A client's interceptor that sends the token.
    pub fn client(&self) -> Result<AddToken> {
        Ok(AddToken::new(self.token()?.as_deref())?)
    }
}

/// What a client needs: the token and, for https:// servers, their CA.
#[derive(Args, Clone, Debug, Default)]
pub struct ClientArgs {
    /// The token to send.
    #[command(flatten)]
    pub token: TokenArgs,
    /// CA certificate (PEM) that signed the server's certificate (https:// URLs).
    #[arg(long, value_name = "FILE")]
    pub tls_ca: Option<PathBuf>,
}

impl ClientArgs {
    /// Token and TLS settings for a connection.
    pub fn access(&self) -> Result<ClientAccess> {
        Ok(ClientAccess {
            token: self.token.client()?,
            tls: self.tls_ca.as_deref().map(client_tls).transpose()?,
        })
    }
}

/// Access settings of a server.
#[derive(Args, Clone, Debug, Default)]
pub struct ServerAccess {
    /// The token to require.
    #[command(flatten)]
    pub token: TokenArgs,
    /// Serve TLS with this certificate chain (PEM); needs --tls-key.
    #[arg(long, value_name = "FILE", requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// The certificate's private key (PEM).
    #[arg(long, value_name = "FILE", requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
    /// Serve a non-loopback address with neither token nor TLS (anyone who reaches the port can
    /// send rollouts and read weights).
    #[arg(long)]
    pub insecure: bool,
}

impl ServerAccess {
    /// The access settings of a server listening on `addr`; refuses an open server
    /// (no token, no TLS) on a non-loopback address unless `--insecure` was given.
    pub fn check(&self, addr: SocketAddr) -> Result<Access> {
        let token = self.token.token()?;
        let tls = match (&self.tls_cert, &self.tls_key) {
            (Some(cert), Some(key)) => {
                let id = Identity::from_pem(read(cert, "certificate")?, read(key, "key")?);
                Some(ServerTlsConfig::new().identity(id))
            }
            _ => None,
        };
        let open = token.is_none() && tls.is_none();
        if open && !addr.ip().is_loopback() {
            if !self.insecure {
                bail!(
                    "refusing to serve {addr} with neither token nor TLS: anyone who reaches \
                     it could feed the learner or read its weights. Give a token (--token, \
                     SAVER_TOKEN or --token-file) and/or --tls-cert and --tls-key or, on a \
                     network you trust, pass --insecure"
                );
            }
            tracing::warn!("serving {addr} with neither token nor TLS (--insecure)");
        }
        Ok(Access {
            check: CheckToken::new(token.as_deref())?,
            tls,
        })
    }

    /// The access settings of a metrics endpoint on `addr`: the same token, TLS
    /// identity and rule as the gRPC port ([`crate::prometheus::MetricsAccess`]).
    pub fn metrics(&self, addr: SocketAddr) -> Result<crate::prometheus::MetricsAccess> {
        let token = self.token.token()?;
        let pem = match (&self.tls_cert, &self.tls_key) {
            (Some(cert), Some(key)) => Some((read(cert, "certificate")?, read(key, "key")?)),
            _ => None,
        };
        crate::prometheus::MetricsAccess::new(
            addr,
            token.as_deref(),
            pem.as_ref().map(|(c, k)| (c.as_slice(), k.as_slice())),
            self.insecure,
        )
    }
}

//! Prometheus `/metrics` for the learner and the pcpn-trainer: the `metrics` crate's
//! recorder (metrics-exporter-prometheus renders the text format) served by a small
//! HTTP/1.1 responder on the role's runtime, so the bound address is known (port 0
//! works) and a slow or hostile scraper costs at most one request of 8 KiB and 5 s.
//!
//! It follows the gRPC port's rule ([`crate::access::ServerAccess`]): with a token
//! every scrape must carry `Authorization: Bearer <token>` (401 otherwise), with a
//! certificate it is HTTPS, and a non-loopback address with neither is refused at
//! start unless `--insecure`.

use anyhow::{bail, Context, Result};
use metrics_exporter_prometheus::{PrometheusBuilder, PrometheusHandle};
use std::net::SocketAddr;
use std::sync::{Arc, OnceLock};
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio_rustls::rustls;
use tokio_rustls::TlsAcceptor;

/// The process's recorder (installed once).
fn handle() -> Result<PrometheusHandle> {
    static HANDLE: OnceLock<PrometheusHandle> = OnceLock::new();
    if let Some(h) = HANDLE.get() {
        return Ok(h.clone());
    }
    let h = PrometheusBuilder::new()
        .install_recorder()
        .context("installing the metrics recorder")?;
    Ok(HANDLE.get_or_init(|| h).clone())
}

/// Who may scrape: the token a scrape must carry and the TLS identity, if any.
#[derive(Clone, Default)]
pub struct MetricsAccess {
    /// `Bearer <token>` as bytes.
    bearer: Option<Arc<[u8]>>,
    /// HTTPS.
    tls: Option<TlsAcceptor>,
}

impl MetricsAccess {
    /// Access for a server on `addr` with `token` and a TLS certificate chain and key
    /// (PEM bytes); refuses a non-loopback address with neither unless `insecure`.
    pub fn new(
        addr: SocketAddr,
        token: Option<&str>,
        tls: Option<(&[u8], &[u8])>,
        insecure: bool,
    ) -> Result<Self> {
        if token.is_none() && tls.is_none() && !addr.ip().is_loopback() {
            if !insecure {
                bail!(
                    "refusing to serve metrics on {addr} with neither token nor TLS: the \
                     same rule as the gRPC port. Give a token (--token, SAVER_TOKEN or \
                     --token-file; scrapers send `Authorization: Bearer <token>`) and/or \
                     --tls-cert and --tls-key, serve them on 127.0.0.1, or, on a network \
                     you trust, pass --insecure"
                );
            }
            tracing::warn!("serving metrics on {addr} with neither token nor TLS (--insecure)");
        }
        let tls = tls.map(|(cert, key)| acceptor(cert, key)).transpose()?;
        Ok(Self {
            bearer: token.map(|t| format!("Bearer {t}").into_bytes().into()),
            tls,
        })
    }

    /// The scheme scrapers use.
    pub fn scheme(&self) -> &'static str {
        if self.tls.is_some() {
            "https"
        } else {
            "http"
        }
    }

    /// Whether the request head `req` may read the metrics.
    fn allows(&self, req: &[u8]) -> bool {
        let Some(want) = &self.bearer else {
            return true;
        };
        let text = String::from_utf8_lossy(req);
        text.split("\r\n").skip(1).any(|line| {
            line.split_once(':').is_some_and(|(name, value)| {
                name.trim().eq_ignore_ascii_case("authorization")
                    && saver_proto::access::same_bytes(value.trim().as_bytes(), want)
            })
        })
    }
}

/// A TLS acceptor for the certificate chain and key in PEM.
fn acceptor(cert: &[u8], key: &[u8]) -> Result<TlsAcceptor> {
    use rustls::pki_types::pem::PemObject;
    use rustls::pki_types::{CertificateDer, PrivateKeyDer};
    let certs = CertificateDer::pem_slice_iter(cert)
        .collect::<std::result::Result<Vec<_>, _>>()
        .context("reading the TLS certificate chain (PEM)")?;
    let key = PrivateKeyDer::from_pem_slice(key).context("reading the TLS key (PEM)")?;
    let config = rustls::ServerConfig::builder_with_provider(Arc::new(
        rustls::crypto::ring::default_provider(),
    ))
    .with_safe_default_protocol_versions()
    .context("TLS protocol versions")?
    .with_no_client_auth()
    .with_single_cert(certs, key)
    .context("the TLS certificate and key")?;
    Ok(TlsAcceptor::from(Arc::new(config)))
}

/// Serves the metrics on `addr` on `rt` for as long as it runs; returns the address
/// bound.
pub fn serve_metrics(
    rt: &tokio::runtime::Runtime,
    addr: SocketAddr,
    access: MetricsAccess,
) -> Result<SocketAddr> {
    let handle = handle()?;
    let listener = rt
        .block_on(tokio::net::TcpListener::bind(addr))
        .with_context(|| format!("listening for metrics scrapes on {addr}"))?;
    let bound = listener.local_addr()?;
    let access = Arc::new(access);
    rt.spawn(async move {
        loop {
            let Ok((sock, _)) = listener.accept().await else {
                // Out of descriptors, say: wait rather than spin.
                tokio::time::sleep(Duration::from_millis(100)).await;
                continue;
            };
            let (handle, access) = (handle.clone(), access.clone());
            tokio::spawn(async move {
                let _ = tokio::time::timeout(Duration::from_secs(5), async {
                    match &access.tls {
                        Some(tls) => {
                            if let Ok(s) = tls.accept(sock).await {
                                answer(s, &handle, &access).await;
                            }
                        }
                        None => answer(sock, &handle, &access).await,
                    }
                })
                .await;
            });
        }
    });
    Ok(bound)
}

/// Reads one request head (8 KiB at most) and answers it.
async fn answer(
    mut sock: impl AsyncRead + AsyncWrite + Unpin,
    handle: &PrometheusHandle,
    access: &MetricsAccess,
) {
    let mut req = Vec::with_capacity(512);
    let mut buf = [0u8; 1024];
    while !req.windows(4).any(|w| w == b"\r\n\r\n") && req.len() < 8192 {
        match sock.read(&mut buf).await {
            Ok(0) | Err(_) => return,
            Ok(n) => req.extend_from_slice(&buf[..n]),
        }
    }
    let reply = if !req.starts_with(b"GET ") {
        "HTTP/1.1 405 Method Not Allowed\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
            .to_string()
    } else if !access.allows(&req) {
        let body = "this endpoint needs the server's token: Authorization: Bearer <token>\n";
        format!(
            "HTTP/1.1 401 Unauthorized\r\nWWW-Authenticate: Bearer\r\nContent-Type: \
             text/plain\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
            body.len()
        )
    } else {
        let body = handle.render();
        format!(
            "HTTP/1.1 200 OK\r\nContent-Type: text/plain; version=0.0.4\r\n\
             Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
            body.len()
        )
    };
    let _ = sock.write_all(reply.as_bytes()).await;
    let _ = sock.shutdown().await;
}

#[cfg(test)]
mod tests {
    use super::*;

    fn addr(s: &str) -> SocketAddr {
        s.parse().unwrap()
    }

    /// A non-loopback address needs a token or TLS (or --insecure); loopback does not.
    #[test]
    fn an_open_non_loopback_endpoint_is_refused_at_start() {
        let e = MetricsAccess::new(addr("0.0.0.0:9100"), None, None, false)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("neither token nor TLS"), "{e}");
        assert!(MetricsAccess::new(addr("0.0.0.0:9100"), Some("s3cret"), None, false).is_ok());
        assert!(MetricsAccess::new(addr("0.0.0.0:9100"), None, None, true).is_ok());
        assert!(MetricsAccess::new(addr("127.0.0.1:9100"), None, None, false).is_ok());
    }

    /// With a token only a request head carrying it (any header case) may read.
    #[test]
    fn scrapes_carry_the_bearer_token() {
        let a = MetricsAccess::new(addr("0.0.0.0:9100"), Some("s3cret"), None, false).unwrap();
        let head = |auth: &str| format!("GET /metrics HTTP/1.1\r\nHost: x\r\n{auth}\r\n\r\n");
        assert!(a.allows(head("Authorization: Bearer s3cret").as_bytes()));
        assert!(a.allows(head("authorization:Bearer s3cret").as_bytes()));
        assert!(!a.allows(head("Authorization: Bearer s3cre").as_bytes()));
        assert!(!a.allows(head("X-Other: 1").as_bytes()));
        let open = MetricsAccess::default();
        assert!(open.allows(head("X-Other: 1").as_bytes()));
    }
}

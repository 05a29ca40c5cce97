//! Connections must earn their place: one that has not passed the token check (made
//! one call through [`crate::CheckToken`]) within [`AUTH_GRACE`] of connecting is
//! closed, so idle or silent connections cannot hold a server's file descriptors.

use std::collections::HashSet;
use std::future::Future;
use std::io;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::TcpStream;
use tonic::transport::server::{Connected, TcpConnectInfo};

/// How long a connection may go without a call that passes the token check.
pub const AUTH_GRACE: Duration = Duration::from_secs(10);

/// Peers (address and port: one per connection) that have passed the token check.
#[derive(Clone, Debug, Default)]
pub struct Admitted(Arc<Mutex<HashSet<SocketAddr>>>);

impl Admitted {
    fn set(&self) -> std::sync::MutexGuard<'_, HashSet<SocketAddr>> {
        self.0.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The connection from `peer` passed the check.
    pub fn admit(&self, peer: SocketAddr) {
        self.set().insert(peer);
    }

    fn contains(&self, peer: &SocketAddr) -> bool {
        self.set().contains(peer)
    }

    fn forget(&self, peer: &SocketAddr) {
        self.set().remove(peer);
    }
}

/// An accepted connection that fails (and so is closed) once `grace` has passed
/// without its peer being admitted.
pub struct Guarded {
    io: TcpStream,
    peer: Option<SocketAddr>,
    admitted: Admitted,
    /// Until the peer is admitted.
    deadline: Option<Pin<Box<tokio::time::Sleep>>>,
}

impl Guarded {
    /// Guards `io`: its peer must be admitted within `grace`.
    pub fn new(io: TcpStream, admitted: Admitted, grace: Duration) -> Self {
        Self {
            peer: io.peer_addr().ok(),
            io,
            admitted,
            deadline: Some(Box::pin(tokio::time::sleep(grace))),
        }
    }

    /// Ok while the peer is admitted or within its grace; the deadline's timer wakes
    /// the connection, so a silent one is closed too.
    fn check(&mut self, cx: &mut Context<'_>) -> io::Result<()> {
        let Some(deadline) = self.deadline.as_mut() else {
            return Ok(());
        };
        if self
            .peer
            .as_ref()
            .is_some_and(|p| self.admitted.contains(p))
        {
            self.deadline = None;
            return Ok(());
        }
        match deadline.as_mut().poll(cx) {
            Poll::Pending => Ok(()),
            Poll::Ready(()) => Err(io::Error::new(
                io::ErrorKind::TimedOut,
                "no authenticated call within the grace period",
            )),
        }
    }
}

impl Drop for Guarded {
    fn drop(&mut self) {
        if let Some(p) = &self.peer {
            self.admitted.forget(p);
        }
    }
}

impl Connected for Guarded {
    type ConnectInfo = TcpConnectInfo;
    fn connect_info(&self) -> TcpConnectInfo {
        self.io.connect_info()
    }
}

impl AsyncRead for Guarded {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        self.check(cx)?;
        Pin::new(&mut self.io).poll_read(cx, buf)
    }
}

impl AsyncWrite for Guarded {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        self.check(cx)?;
        Pin::new(&mut self.io).poll_write(cx, buf)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.io).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.io).poll_shutdown(cx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    #[tokio::test]
    async fn a_silent_connection_is_closed_and_an_admitted_one_kept() {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let admitted = Admitted::default();
        let grace = Duration::from_millis(100);

        // Never admitted: the server side's read fails once the grace is over, though
        // the client sends nothing.
        let _silent = TcpStream::connect(addr).await.unwrap();
        let (io, _) = listener.accept().await.unwrap();
        let mut guarded = Guarded::new(io, admitted.clone(), grace);
        let e = guarded.read(&mut [0u8; 8]).await.unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::TimedOut);

        // Admitted (its call passed the token check): reads go on past the grace.
        let mut client = TcpStream::connect(addr).await.unwrap();
        let (io, peer) = listener.accept().await.unwrap();
        let mut guarded = Guarded::new(io, admitted.clone(), grace);
        admitted.admit(peer);
        tokio::time::sleep(2 * grace).await;
        client.write_all(b"hi").await.unwrap();
        let mut got = [0u8; 2];
        guarded.read_exact(&mut got).await.unwrap();
        assert_eq!(&got, b"hi");
        // Closing forgets the peer.
        drop(guarded);
        assert!(!admitted.contains(&peer));
    }
}

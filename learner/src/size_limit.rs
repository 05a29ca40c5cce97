//! The size of each rollout message, bounded per stream before it is buffered or
//! decoded. A registration fixes the exact shape of its rollouts (envs × steps × the
//! env layout), so the largest legal encoding of one is known; a StreamRollouts call
//! that names its registration (metadata x-saver-actor-id and x-saver-session) may
//! send messages up to that size, and the stream ends with RESOURCE_EXHAUSTED at the
//! first gRPC length prefix above it — far below the server-wide 64 MiB, so a client
//! cannot make the learner buffer and decode (and amplify) huge messages.

use crate::Hub;
use bytes::Bytes;
use http_body::{Body as HttpBody, Frame};
use saver_core::config::RunConfig;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use tonic::body::Body;
use tonic::Status;

/// The gRPC path of StreamRollouts.
const STREAM_ROLLOUTS: &str = "/saver.v1.Learner/StreamRollouts";

/// The largest encoding of a rollout of `n_envs` envs of `config`'s run, counting
/// every repeated field unpacked (the costliest legal encoding) and every episode
/// and timeout that can exist, plus 1 KiB for the scalar fields.
pub fn max_rollout_bytes(config: &RunConfig, n_envs: usize) -> usize {
    let l = config.env.layout();
    let (e, n) = (n_envs, config.rollout as usize);
    let steps = e * n;
    let floats = e * (n + 1) * l.obs_dim
        + steps * (l.mu_dim() + l.log_std_dim() + l.action_dim() + 2 * l.aligned_dim)
        + steps * l.obs_dim; // timeout_obs: at most one per step
                             // Per value: a 1-byte tag and a float (5), a bool (2), a u32 varint (6); an
                             // episode: tag, length, and its three fields (2 + 6 + 2 + 5).
    5 * floats + 2 * steps + 6 * steps + 15 * steps + 1024
}

/// A tower layer for the learner's server: bounds StreamRollouts messages per stream.
#[derive(Clone)]
pub struct RolloutSizeLimit {
    hub: Arc<Hub>,
}

impl RolloutSizeLimit {
    /// The limit for `hub`'s registrations.
    pub fn new(hub: Arc<Hub>) -> Self {
        Self { hub }
    }
}

impl<S> tower_layer::Layer<S> for RolloutSizeLimit {
    type Service = LimitedService<S>;
    fn layer(&self, inner: S) -> Self::Service {
        LimitedService {
            inner,
            hub: self.hub.clone(),
        }
    }
}

/// The service [`RolloutSizeLimit`] wraps.
#[derive(Clone)]
pub struct LimitedService<S> {
    inner: S,
    hub: Arc<Hub>,
}

impl<S, R> tower_service::Service<http::Request<Body>> for LimitedService<S>
where
    S: tower_service::Service<http::Request<Body>, Response = R>,
{
    type Response = R;
    type Error = S::Error;
    type Future = S::Future;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, req: http::Request<Body>) -> Self::Future {
        if req.uri().path() != STREAM_ROLLOUTS {
            return self.inner.call(req);
        }
        let header = |k: &str| {
            req.headers()
                .get(k)
                .and_then(|v| v.to_str().ok())
                .and_then(|v| v.parse::<u64>().ok())
        };
        let owner = header(saver_proto::ACTOR_ID_KEY)
            .and_then(|id| u32::try_from(id).ok())
            .zip(header(saver_proto::SESSION_KEY));
        let config = self.hub.config();
        // A stream that names a registration gets its exact shape; one that names
        // none (it claims one with its first rollout) the largest registration's.
        let n_envs = match owner {
            Some((id, session)) => self.hub.registered_envs(id, session).unwrap_or(1),
            None => crate::hub::MAX_ENVS,
        };
        let limit = max_rollout_bytes(config, n_envs).min(saver_proto::MAX_MESSAGE_BYTES);
        let req = req.map(|body| {
            Body::new(LimitedBody {
                inner: body,
                limit,
                n_envs,
                header: [0; 5],
                header_len: 0,
                remaining: 0,
            })
        });
        self.inner.call(req)
    }
}

/// A request body that follows the gRPC framing (a 5-byte prefix: compression flag
/// and big-endian length, then the message) and fails at the first prefix whose
/// length is over `limit`.
struct LimitedBody {
    inner: Body,
    limit: usize,
    n_envs: usize,
    /// The prefix being read.
    header: [u8; 5],
    header_len: usize,
    /// Message bytes still to come before the next prefix.
    remaining: usize,
}

impl LimitedBody {
    /// Follows the framing through `data`; the first length over the limit is an error.
    fn scan(&mut self, mut data: &[u8]) -> Result<(), Status> {
        while !data.is_empty() {
            if self.remaining > 0 {
                let take = self.remaining.min(data.len());
                self.remaining -= take;
                data = &data[take..];
                continue;
            }
            let take = (5 - self.header_len).min(data.len());
            self.header[self.header_len..self.header_len + take].copy_from_slice(&data[..take]);
            self.header_len += take;
            data = &data[take..];
            if self.header_len == 5 {
                self.header_len = 0;
                let len = u32::from_be_bytes([
                    self.header[1],
                    self.header[2],
                    self.header[3],
                    self.header[4],
                ]) as usize;
                if len > self.limit {
                    return Err(Status::resource_exhausted(format!(
                        "a rollout message of {len} bytes is over this stream's limit of {} \
                         bytes (the largest rollout of {} envs)",
                        self.limit, self.n_envs
                    )));
                }
                self.remaining = len;
            }
        }
        Ok(())
    }
}

impl HttpBody for LimitedBody {
    type Data = Bytes;
    type Error = Status;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, Status>>> {
        let this = &mut *self;
        match Pin::new(&mut this.inner).poll_frame(cx) {
            Poll::Ready(Some(Ok(frame))) => {
                if let Some(data) = frame.data_ref() {
                    if let Err(s) = this.scan(data) {
                        return Poll::Ready(Some(Err(s)));
                    }
                }
                Poll::Ready(Some(Ok(frame)))
            }
            other => other,
        }
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use saver_core::config::Algo;
    use saver_core::env::{EnvKind, EnvSpec};

    #[test]
    fn the_limit_is_the_largest_encoding_of_the_registered_shape() {
        // angle d = 4, n = 8, one env: floats = 9·4 (obs) + 8·(4 + 4 + 4 + 8) + 8·4
        // (timeout_obs) = 228 → 1140 bytes; 8 steps · (2 + 6 + 15) = 184; + 1024.
        let config = RunConfig::paper(&EnvSpec::new(EnvKind::Angle, 4).unwrap(), Algo::A2c, 0);
        assert_eq!(config.rollout, 8);
        assert_eq!(max_rollout_bytes(&config, 1), 1140 + 184 + 1024);
        // A real rollout's encoding fits with room to spare.
        let body = |len: u32| {
            let mut b = vec![0u8];
            b.extend_from_slice(&len.to_be_bytes());
            b
        };
        let mut l = LimitedBody {
            inner: Body::empty(),
            limit: 2348,
            n_envs: 1,
            header: [0; 5],
            header_len: 0,
            remaining: 0,
        };
        // Two messages, the second prefix split across chunks: fine; then one over.
        let mut chunk = body(2000);
        chunk.extend(vec![7u8; 2000]);
        chunk.extend(&body(2348)[..3]);
        l.scan(&chunk).unwrap();
        let mut rest = body(2348)[3..].to_vec();
        rest.extend(vec![7u8; 2348]);
        l.scan(&rest).unwrap();
        let e = l.scan(&body(2349)).unwrap_err();
        assert_eq!(e.code(), tonic::Code::ResourceExhausted);
    }
}

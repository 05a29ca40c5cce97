//! Who may talk to a server: the shared token (flag, SAVER_TOKEN or a file) that every
//! server checks and every client sends, and the refusal to serve a non-loopback
//! address without one unless the user says `--insecure`.

use anyhow::{bail, Context, Result};
use clap::Args;
use saver_proto::{AddToken, CheckToken};
use std::net::SocketAddr;
use std::path::PathBuf;

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

impl TokenArgs {
    /// The token, if one was given.
    pub fn token(&self) -> Result<Option<String>> {
        let token = match (&self.token, &self.token_file) {
            (Some(t), _) => Some(t.clone()),
            (None, Some(path)) => {
                let text = std::fs::read_to_string(path)
                    .with_context(|| format!("reading the token file {}", path.display()))?;
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

/// Access settings of a server.
#[derive(Args, Clone, Debug, Default)]
pub struct ServerAccess {
    /// The token to require.
    #[command(flatten)]
    pub token: TokenArgs,
    /// Serve a non-loopback address with no token (anyone who reaches the port can
    /// send rollouts and read weights).
    #[arg(long)]
    pub insecure: bool,
}

impl ServerAccess {
    /// The token check for a server listening on `addr`; refuses an open server on a
    /// non-loopback address unless `--insecure` was given.
    pub fn check(&self, addr: SocketAddr) -> Result<CheckToken> {
        let token = self.token.token()?;
        if token.is_none() && !addr.ip().is_loopback() && !self.insecure {
            bail!(
                "refusing to serve {addr} without a token: anyone who reaches it could feed \
                 the learner or read its weights. Give a token (--token, SAVER_TOKEN or \
                 --token-file) or, on a network you trust, pass --insecure"
            );
        }
        if token.is_none() && !addr.ip().is_loopback() {
            tracing::warn!("serving {addr} with no token (--insecure)");
        }
        Ok(CheckToken::new(token.as_deref())?)
    }
}

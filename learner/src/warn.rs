//! Warnings that a client can cause, rate-limited: the first is logged, the ones
//! after it within [`QUIET`] are counted and reported with the next one logged, so a
//! flood of bad rollouts costs a log line every few seconds, not one each.

use std::sync::Mutex;
use std::time::{Duration, Instant};

/// At most one line per kind of warning in this long.
pub const QUIET: Duration = Duration::from_secs(5);

/// One kind of warning.
#[derive(Debug, Default)]
pub struct RateLimited {
    /// When the last line was written, and how many were held back since.
    state: Mutex<(Option<Instant>, u64)>,
}

impl RateLimited {
    /// Logs `message()` now, with the count held back since the last line, or counts it
    /// when a line was written less than [`QUIET`] ago. Returns whether it logged.
    pub fn warn(&self, message: impl FnOnce() -> String) -> bool {
        let mut s = self.state.lock().unwrap_or_else(|e| e.into_inner());
        let now = Instant::now();
        if s.0.is_some_and(|last| now.duration_since(last) < QUIET) {
            s.1 += 1;
            return false;
        }
        let held = std::mem::take(&mut s.1);
        s.0 = Some(now);
        drop(s);
        if held > 0 {
            tracing::warn!("{} ({held} more like it in the last {QUIET:?})", message());
        } else {
            tracing::warn!("{}", message());
        }
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_flood_logs_one_line_and_counts_the_rest() {
        let w = RateLimited::default();
        assert!(w.warn(|| "first".into()));
        let logged = (0..10_000).filter(|_| w.warn(|| "again".into())).count();
        assert_eq!(logged, 0);
        assert_eq!(w.state.lock().unwrap().1, 10_000);
    }
}

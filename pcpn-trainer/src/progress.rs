//! How far the store's pretraining is: its samples (from the [`SampleHub`]) and its
//! batches, for the store's log every 10 s and the Progress RPC (the learner that
//! waits for the PCPN asks it, and says it on; so do its actors and `saver status`).

use crate::samples::{SampleHub, SampleProgress};
use saver_core::env::EnvSpec;
use saver_proto::pb;
use std::sync::{Arc, Mutex};
use std::time::Instant;

/// The batches of the pretraining in progress.
#[derive(Clone, Debug)]
struct Batches {
    spec: EnvSpec,
    done: u64,
    of: u64,
    /// When the pretraining began.
    since: Instant,
    /// When its first batch was done (the batch rate is timed from there).
    first: Option<(Instant, u64)>,
    loss: f32,
}

/// The pretraining in progress, shared by the pretraining thread and the service.
#[derive(Clone, Default)]
pub struct Tracker {
    batches: Arc<Mutex<Option<Batches>>>,
}

impl Tracker {
    fn lock(&self) -> std::sync::MutexGuard<'_, Option<Batches>> {
        self.batches.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// A pretraining of `spec` for `of` batches begins.
    pub fn begin(&self, spec: &EnvSpec, of: u64) {
        *self.lock() = Some(Batches {
            spec: spec.clone(),
            done: 0,
            of,
            since: Instant::now(),
            first: None,
            loss: f32::NAN,
        });
    }

    /// `done` batches are done; the last one's loss.
    pub fn batch(&self, done: u64, loss: f32) {
        if let Some(b) = self.lock().as_mut() {
            b.done = done;
            b.loss = loss;
            b.first.get_or_insert((Instant::now(), done));
        }
    }

    /// It ended (stored or failed).
    pub fn end(&self) {
        *self.lock() = None;
    }

    /// How far it is, with its samples from `hub`: None when none is in progress.
    pub fn progress(&self, hub: &SampleHub) -> Option<pb::PretrainProgress> {
        let b = self.lock().clone()?;
        let samples = hub.progress().filter(|s| s.spec == b.spec.dynamics());
        Some(progress_of(&b, samples.as_ref()))
    }
}

/// The message (and its one-line form) of a pretraining's batches and samples.
fn progress_of(b: &Batches, samples: Option<&SampleProgress>) -> pb::PretrainProgress {
    let seconds = b.since.elapsed().as_secs_f64();
    let gathering = samples.is_some_and(|s| s.received < s.total) && b.done == 0;
    let batch_eta = b.first.and_then(|(at, from)| {
        let rate = (b.done - from) as f64 / at.elapsed().as_secs_f64().max(1e-9);
        (b.done > from).then(|| (b.of - b.done) as f64 / rate)
    });
    let (phase, eta) = if gathering {
        ("samples", samples.and_then(SampleProgress::eta))
    } else {
        ("batches", batch_eta)
    };
    let batches = if b.done == 0 {
        format!("then {} batches", b.of)
    } else {
        let rate = b.first.map_or(0.0, |(at, from)| {
            (b.done - from) as f64 / at.elapsed().as_secs_f64().max(1e-9)
        });
        let eta = batch_eta.map_or_else(String::new, |s| format!(", about {s:.0} s left"));
        format!(
            "batch {} of {} ({:.0} %), {rate:.0} batches/s{eta}, loss {:.4}",
            b.done,
            b.of,
            100.0 * b.done as f64 / b.of.max(1) as f64,
            b.loss
        )
    };
    let line = match samples {
        Some(s) if s.received < s.total => {
            let none = if s.providers == 0 {
                "; no actor streams samples of it: start its actors with --pcpn-samples at \
                 this store's address (Python: saver-actor act --pcpn-samples URL)"
            } else {
                ""
            };
            format!("pretraining {}: {}; {batches}{none}", b.spec, s.line())
        }
        _ => format!("pretraining {}: {batches}", b.spec),
    };
    pb::PretrainProgress {
        env: Some((&b.spec).into()),
        phase: phase.into(),
        samples_received: samples.map_or(0, |s| s.received),
        samples_total: samples.map_or(0, |s| s.total),
        providers: samples.map_or(0, |s| s.providers as u32),
        batches_done: b.done,
        batches: b.of,
        seconds,
        eta_seconds: eta.unwrap_or(-1.0),
        line,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The line and the fields say the phase, the counts and the time left.
    #[test]
    fn progress_says_samples_then_batches() {
        let spec = EnvSpec::unit_custom("line", 0.1).unwrap();
        let mut b = Batches {
            spec: spec.clone(),
            done: 0,
            of: 5_000,
            since: Instant::now(),
            first: None,
            loss: f32::NAN,
        };
        let s = SampleProgress {
            spec,
            received: 16_384,
            total: 65_536,
            providers: 0,
            seconds: 4.0,
        };
        let p = progress_of(&b, Some(&s));
        assert_eq!(
            (p.phase.as_str(), p.samples_received, p.samples_total),
            ("samples", 16_384, 65_536)
        );
        // 16,384 in 4 s: 4,096/s, and 49,152 left: 12 s.
        assert!((p.eta_seconds - 12.0).abs() < 1e-9, "{}", p.eta_seconds);
        for part in [
            "16384 of 65536 samples (25 %) from 0 providers, 4096/s, about 12 s left",
            "then 5000 batches",
            "--pcpn-samples",
        ] {
            assert!(p.line.contains(part), "{part:?} not in {:?}", p.line);
        }
        b.done = 10;
        b.first = Some((Instant::now() - std::time::Duration::from_secs(2), 0));
        b.loss = 0.25;
        let p = progress_of(&b, None);
        assert_eq!(
            (p.phase.as_str(), p.batches_done, p.batches),
            ("batches", 10, 5_000)
        );
        // 10 batches in ~2 s: ~5/s, 4,990 left: ~998 s.
        assert!((p.eta_seconds - 998.0).abs() < 5.0, "{}", p.eta_seconds);
        assert!(
            p.line.contains("batch 10 of 5000 (0 %)") && p.line.contains("loss 0.2500"),
            "{}",
            p.line
        );
    }
}

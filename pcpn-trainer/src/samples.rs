//! Pretraining samples streamed by actors (saver.proto `ProvideSamples`;
//! docs/ALGORITHM.md §9.7). The store cannot step a custom env, so the actors that
//! bring it draw the transitions ("walk" samples) and the store pretrains from them.
//!
//! A [`SampleHub`] sits between the providers' streams (async, thin) and the
//! pretraining thread (blocking): the pretraining asks for a number of samples; each
//! connected provider of that env is handed demands of [`CHUNK`] samples while fewer
//! than [`QUEUED_CHUNKS`] chunks are queued or on their way; what arrives is checked
//! against the env's layout and bounds, queued, and read through a shuffle buffer of
//! [`SHUFFLE`] samples (a provider's chunk is consecutive steps of its walks; the
//! buffer mixes providers and times). A provider that leaves mid-chunk gives its
//! unfilled part back to the others; one that sends a bad sample is cut off with
//! INVALID_ARGUMENT and its chunk is given back too.

use rand::Rng;
use saver_core::env::slack;
use saver_core::env::EnvSpec;
use saver_core::pretrain::{SampleSource, Samples};
use saver_core::rng::{rng_for, SaverRng};
use saver_core::{CoreError, Result};
use saver_proto::pb;
use std::collections::VecDeque;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

/// Samples per demand.
pub const CHUNK: u32 = 4096;
/// Chunks queued or on their way at most (bounds the store's memory).
pub const QUEUED_CHUNKS: u64 = 8;
/// Samples in the shuffle buffer.
pub const SHUFFLE: usize = 65_536;
/// How often the store says how far a pretraining is (and the learner, and actors).
pub const SAY_EVERY: Duration = Duration::from_secs(10);
/// How long a pretraining waits for its next samples unless told otherwise
/// (`saver pcpn-trainer --pretrain-deadline`).
pub const DEFAULT_DEADLINE: Duration = Duration::from_secs(30 * 60);

/// What the pretraining in progress wants.
struct Want {
    /// The env it pretrains for.
    spec: EnvSpec,
    /// Samples not yet demanded of any provider.
    unassigned: u64,
    /// Samples demanded and not yet arrived.
    in_flight: u64,
    /// Arrived, checked, not yet read.
    queued: VecDeque<Samples>,
    /// Samples received so far.
    received: u64,
    /// Of.
    total: u64,
    /// When the pretraining asked for them.
    since: Instant,
}

/// How far the samples of the pretraining in progress are (saver.proto
/// PretrainProgress).
#[derive(Clone, Debug, PartialEq)]
pub struct SampleProgress {
    /// The env.
    pub spec: EnvSpec,
    /// Samples arrived.
    pub received: u64,
    /// Of.
    pub total: u64,
    /// Providers of that env connected.
    pub providers: usize,
    /// Seconds since the pretraining asked for them.
    pub seconds: f64,
}

impl SampleProgress {
    /// Seconds until the rest arrive at the rate so far (None before the first).
    pub fn eta(&self) -> Option<f64> {
        (self.received > 0 && self.seconds > 0.0).then(|| {
            (self.total - self.received.min(self.total)) as f64 * self.seconds
                / self.received as f64
        })
    }

    /// "12288 of 67584 samples (18 %) from 2 providers, 3100/s, about 18 s left".
    pub fn line(&self) -> String {
        let rate = self.received as f64 / self.seconds.max(1e-9);
        let eta = self
            .eta()
            .map_or_else(String::new, |s| format!(", about {s:.0} s left"));
        format!(
            "{} of {} samples ({:.0} %) from {} providers, {rate:.0}/s{eta}",
            self.received,
            self.total,
            100.0 * self.received as f64 / self.total.max(1) as f64,
            self.providers
        )
    }
}

#[derive(Default)]
struct HubState {
    /// The pretraining that waits for samples (one at a time).
    want: Option<Want>,
    /// Connected providers: their env.
    providers: Vec<(u64, EnvSpec)>,
    /// Next provider id.
    next_id: u64,
}

/// Connects sample providers to the pretraining that needs their samples.
pub struct SampleHub {
    state: Mutex<HubState>,
    /// Samples arrived (wakes the pretraining thread).
    arrived: Condvar,
    /// Work may be there (wakes the providers' tasks).
    work: tokio::sync::watch::Sender<u64>,
    /// How long a pretraining waits for its next samples before it fails.
    deadline: Duration,
    /// The store is stopping: a waiting pretraining ends at once.
    cancelled: std::sync::atomic::AtomicBool,
}

impl Default for SampleHub {
    fn default() -> Self {
        Self::with_deadline(DEFAULT_DEADLINE)
    }
}

impl SampleHub {
    /// A hub whose pretraining fails when no samples arrive for `deadline` (at the
    /// start, or after the last ones).
    pub fn with_deadline(deadline: Duration) -> Self {
        Self {
            state: Mutex::default(),
            arrived: Condvar::new(),
            work: tokio::sync::watch::channel(0).0,
            deadline,
            cancelled: Default::default(),
        }
    }

    /// Ends the wait of a pretraining for samples (with an error saying the store
    /// stops), now and from now on.
    pub fn cancel(&self) {
        self.cancelled
            .store(true, std::sync::atomic::Ordering::SeqCst);
        let _s = self.lock();
        self.arrived.notify_all();
    }

    /// The samples of the pretraining in progress, if one waits for streamed samples.
    pub fn progress(&self) -> Option<SampleProgress> {
        let s = self.lock();
        let w = s.want.as_ref()?;
        Some(SampleProgress {
            spec: w.spec.clone(),
            received: w.received,
            total: w.total,
            providers: s.providers.iter().filter(|(_, p)| *p == w.spec).count(),
            seconds: w.since.elapsed().as_secs_f64(),
        })
    }

    fn lock(&self) -> MutexGuard<'_, HubState> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn wake_providers(&self) {
        self.work.send_modify(|g| *g += 1);
    }

    /// Providers connected for `spec`.
    pub fn providers_of(&self, spec: &EnvSpec) -> usize {
        self.lock()
            .providers
            .iter()
            .filter(|(_, s)| *s == spec.dynamics())
            .count()
    }

    /// A provider of `spec` joins; its id.
    fn join(&self, spec: EnvSpec) -> u64 {
        let mut s = self.lock();
        let id = s.next_id;
        s.next_id += 1;
        tracing::info!("sample provider {id} for {spec} connected");
        s.providers.push((id, spec));
        id
    }

    fn leave(&self, id: u64) {
        self.lock().providers.retain(|(p, _)| *p != id);
    }

    /// A demand for provider of `spec`, if the pretraining needs one now: (count,
    /// received, total).
    fn take(&self, spec: &EnvSpec) -> Option<(u32, u64, u64)> {
        let mut s = self.lock();
        let w = s.want.as_mut().filter(|w| &w.spec == spec)?;
        let queued: u64 = w.queued.iter().map(|q| q.n as u64).sum();
        if w.unassigned == 0 || queued + w.in_flight >= QUEUED_CHUNKS * CHUNK as u64 {
            return None;
        }
        let n = w.unassigned.min(CHUNK as u64);
        w.unassigned -= n;
        w.in_flight += n;
        Some((n as u32, w.received, w.total))
    }

    /// Checked samples of `spec` arrived.
    fn deliver(&self, spec: &EnvSpec, samples: Samples) {
        let mut s = self.lock();
        if let Some(w) = s.want.as_mut().filter(|w| &w.spec == spec) {
            let n = samples.n as u64;
            w.in_flight = w.in_flight.saturating_sub(n);
            w.received += n;
            w.queued.push_back(samples);
            self.arrived.notify_all();
        }
    }

    /// `n` demanded samples of `spec` will not come: they go to another provider.
    fn give_back(&self, spec: &EnvSpec, n: u64) {
        let mut s = self.lock();
        if let Some(w) = s.want.as_mut().filter(|w| &w.spec == spec) {
            w.in_flight = w.in_flight.saturating_sub(n);
            w.unassigned += n;
        }
        drop(s);
        self.wake_providers();
    }

    /// A source of `total` streamed samples of `spec` (refused while another
    /// pretraining waits for samples), drawn through a shuffle buffer seeded by `seed`.
    pub fn source(self: &Arc<Self>, spec: &EnvSpec, total: u64, seed: u64) -> Result<Streamed> {
        // Providers are matched on what the PCPN models (their specs are stored so).
        let spec = &spec.dynamics();
        let mut s = self.lock();
        if let Some(w) = &s.want {
            return Err(CoreError::Config(format!(
                "samples of {} are being gathered for another pretraining",
                w.spec
            )));
        }
        s.want = Some(Want {
            spec: spec.clone(),
            unassigned: total,
            in_flight: 0,
            queued: VecDeque::new(),
            received: 0,
            total,
            since: Instant::now(),
        });
        drop(s);
        self.wake_providers();
        Ok(Streamed {
            hub: self.clone(),
            spec: spec.clone(),
            buffer: Samples {
                x: Vec::new(),
                delta: Vec::new(),
                n: 0,
            },
            pending: VecDeque::new(),
            left: total,
            rng: rng_for(seed, saver_core::rng::streams::PRETRAIN),
        })
    }

    /// The next chunk of samples for the pretraining of `spec`; waits (saying how far
    /// the samples are every 10 s) until one arrives, and fails when none has for the
    /// hub's deadline or the store stops.
    fn next_chunk(&self, spec: &EnvSpec) -> Result<Samples> {
        let mut s = self.lock();
        let since = Instant::now();
        loop {
            if let Some(chunk) = s.want.as_mut().and_then(|w| w.queued.pop_front()) {
                drop(s);
                self.wake_providers();
                return Ok(chunk);
            }
            if self.cancelled.load(std::sync::atomic::Ordering::SeqCst) {
                return Err(CoreError::Config(format!(
                    "pretraining {spec}: the store is stopping"
                )));
            }
            let left = self.deadline.saturating_sub(since.elapsed());
            let providers = s.providers.iter().filter(|(_, p)| p == spec).count();
            let (got, of) = s.want.as_ref().map_or((0, 0), |w| (w.received, w.total));
            if left.is_zero() {
                return Err(CoreError::Config(format!(
                    "pretraining {spec}: no samples arrived for {:?} ({providers} sample \
                     providers connected; {got} of {of} samples arrived). It waits for the \
                     env's actors to stream samples: start them with --pcpn-samples at this \
                     store's address (Python: saver-actor act --pcpn-samples URL), or give \
                     the store more time with --pretrain-deadline",
                    self.deadline
                )));
            }
            s = self
                .arrived
                .wait_timeout(s, left.min(Duration::from_millis(250)))
                .unwrap_or_else(|p| p.into_inner())
                .0;
        }
    }

    fn finish(&self) {
        self.lock().want = None;
        self.wake_providers();
    }
}

/// Samples streamed by the providers of one env, read through a shuffle buffer:
/// each arriving sample is used once.
pub struct Streamed {
    hub: Arc<SampleHub>,
    spec: EnvSpec,
    /// The shuffle buffer.
    buffer: Samples,
    /// Arrived samples not yet in the buffer (rows from `pending.front()` onward).
    pending: VecDeque<(Samples, usize)>,
    /// Samples not yet taken from the hub.
    left: u64,
    rng: SaverRng,
}

impl Drop for Streamed {
    fn drop(&mut self) {
        self.hub.finish();
    }
}

impl Streamed {
    /// The next arrived sample (x row, delta row), if any is left; fails when the
    /// providers stopped giving them ([`SampleHub::next_chunk`]).
    fn next_row(&mut self) -> Result<Option<(Vec<f32>, Vec<f32>)>> {
        let l = self.spec.layout();
        let (xw, d) = (l.pcpn_input_dim(), l.aligned_dim);
        loop {
            if let Some((chunk, at)) = self.pending.front_mut() {
                if *at < chunk.n {
                    let i = *at;
                    *at += 1;
                    return Ok(Some((
                        chunk.x[i * xw..(i + 1) * xw].to_vec(),
                        chunk.delta[i * d..(i + 1) * d].to_vec(),
                    )));
                }
                self.pending.pop_front();
                continue;
            }
            if self.left == 0 {
                return Ok(None);
            }
            let chunk = self.hub.next_chunk(&self.spec)?;
            self.left = self.left.saturating_sub(chunk.n as u64);
            self.pending.push_back((chunk, 0));
        }
    }

    /// The next `n` samples in the order they arrived.
    fn rows(&mut self, n: usize) -> Result<Samples> {
        let mut s = Samples {
            x: Vec::new(),
            delta: Vec::new(),
            n: 0,
        };
        while s.n < n {
            let (x, d) = self.next_row()?.ok_or_else(|| exhausted(n - s.n))?;
            s.x.extend(x);
            s.delta.extend(d);
            s.n += 1;
        }
        Ok(s)
    }

    /// The first `n` samples in the order they arrived, apart from the rest (a
    /// held-out set).
    pub fn held_out(&mut self, n: usize) -> Result<Replay> {
        Ok(Replay {
            layout: self.spec.layout(),
            samples: self.rows(n)?,
            at: 0,
        })
    }

    /// The next `n` arrived samples as a [`Pool`] drawn from at random with
    /// replacement (seeded like this source); the providers are asked for no more.
    pub fn into_pool(mut self, n: usize) -> Result<Pool> {
        Ok(Pool {
            layout: self.spec.layout(),
            samples: self.rows(n)?,
            rng: self.rng.clone(),
        })
    }
}

/// A fixed set of streamed samples that batches draw from at random, with
/// replacement (`pretrain.walk_samples`).
pub struct Pool {
    layout: saver_core::env::EnvLayout,
    samples: Samples,
    rng: SaverRng,
}

impl SampleSource for Pool {
    fn layout(&self) -> saver_core::env::EnvLayout {
        self.layout
    }

    fn sample(&mut self, n: usize) -> Result<Samples> {
        let rows: Vec<usize> = (0..n)
            .map(|_| self.rng.random_range(0..self.samples.n))
            .collect();
        Ok(gather(&self.samples, self.layout, &rows))
    }
}

fn exhausted(n: usize) -> CoreError {
    CoreError::Config(format!(
        "pretraining asked for more streamed samples than it announced ({n} more)"
    ))
}

impl SampleSource for Streamed {
    fn layout(&self) -> saver_core::env::EnvLayout {
        self.spec.layout()
    }

    fn sample(&mut self, n: usize) -> Result<Samples> {
        let l = self.spec.layout();
        let (xw, d) = (l.pcpn_input_dim(), l.aligned_dim);
        while self.buffer.n < SHUFFLE {
            let Some((x, dl)) = self.next_row()? else {
                break;
            };
            self.buffer.x.extend(x);
            self.buffer.delta.extend(dl);
            self.buffer.n += 1;
        }
        let mut out = Samples {
            x: Vec::with_capacity(n * xw),
            delta: Vec::with_capacity(n * d),
            n,
        };
        for _ in 0..n {
            if self.buffer.n == 0 {
                return Err(exhausted(n));
            }
            let i = self.rng.random_range(0..self.buffer.n);
            out.x
                .extend_from_slice(&self.buffer.x[i * xw..(i + 1) * xw]);
            out.delta
                .extend_from_slice(&self.buffer.delta[i * d..(i + 1) * d]);
            // The slot takes the next arrival, or the buffer's last sample.
            let (x, dl) = match self.next_row()? {
                Some(row) => row,
                None => {
                    let last = self.buffer.n - 1;
                    let row = (
                        self.buffer.x[last * xw..].to_vec(),
                        self.buffer.delta[last * d..].to_vec(),
                    );
                    self.buffer.x.truncate(last * xw);
                    self.buffer.delta.truncate(last * d);
                    self.buffer.n = last;
                    if i == last {
                        continue;
                    }
                    row
                }
            };
            self.buffer.x[i * xw..(i + 1) * xw].copy_from_slice(&x);
            self.buffer.delta[i * d..(i + 1) * d].copy_from_slice(&dl);
        }
        Ok(out)
    }
}

/// A fixed set of samples, served in order and again from the start (the held-out
/// set: the loss before and after pretraining is measured on the same samples).
pub struct Replay {
    layout: saver_core::env::EnvLayout,
    samples: Samples,
    at: usize,
}

impl SampleSource for Replay {
    fn layout(&self) -> saver_core::env::EnvLayout {
        self.layout
    }

    fn sample(&mut self, n: usize) -> Result<Samples> {
        let rows: Vec<usize> = (self.at..self.at + n)
            .map(|i| i % self.samples.n.max(1))
            .collect();
        self.at += n;
        Ok(gather(&self.samples, self.layout, &rows))
    }
}

/// Rows `rows` of `from` (samples of `layout`), in that order.
fn gather(from: &Samples, layout: saver_core::env::EnvLayout, rows: &[usize]) -> Samples {
    let (xw, d) = (layout.pcpn_input_dim(), layout.aligned_dim);
    let mut out = Samples {
        x: Vec::with_capacity(rows.len() * xw),
        delta: Vec::with_capacity(rows.len() * d),
        n: rows.len(),
    };
    for &i in rows {
        out.x.extend_from_slice(&from.x[i * xw..(i + 1) * xw]);
        out.delta.extend_from_slice(&from.delta[i * d..(i + 1) * d]);
    }
    out
}

/// A provider's batch as samples of `spec`, at most `room` of them, every value
/// checked: lengths, finite, obs within the env's bounds, μ in [-1, 1], log σ in
/// [ln 1e-10, 0], each aligned change within the env's largest step.
pub fn check_batch(spec: &EnvSpec, b: &pb::SampleBatch, room: u32) -> Result<Samples> {
    let l = spec.layout();
    let bounds = spec.bounds();
    let bad = |why: String| Err(CoreError::Data(format!("sample batch for {spec}: {why}")));
    let n = b.n as usize;
    if b.n == 0 || b.n > room {
        return bad(format!(
            "n = {} where 1..={room} samples are still owed",
            b.n
        ));
    }
    for (what, len, width) in [
        ("obs", b.obs.len(), l.obs_dim),
        ("mu", b.mu.len(), l.mu_dim()),
        ("log_std", b.log_std.len(), l.log_std_dim()),
        ("delta", b.delta.len(), l.aligned_dim),
    ] {
        if len != n * width {
            return bad(format!(
                "{what} has {len} values, not n x {width} = {}",
                n * width
            ));
        }
    }
    if let Some((i, k)) = bounds.obs_outside(&b.obs) {
        let (v, lo, hi) = (b.obs[i], bounds.obs_low[k], bounds.obs_high[k]);
        return bad(format!(
            "sample {}: observation entry {k} = {v} is outside the env's declared bounds \
             [{lo}, {hi}]",
            i / l.obs_dim
        ));
    }
    let m = l.mu_dim();
    if let Some(i) =
        b.mu.iter()
            .position(|v| v.is_nan() || v.abs() > 1.0 + slack(1.0))
    {
        let (s, j, v) = (i / m, i % m, b.mu[i]);
        return bad(format!("sample {s}: mu[{j}] = {v} is outside [-1, 1]"));
    }
    let (lo, c) = ((1e-10f32).ln(), l.log_std_dim());
    if let Some(i) = b
        .log_std
        .iter()
        .position(|v| !(lo - slack(lo)..=slack(0.0)).contains(v))
    {
        let (s, j, v) = (i / c, i % c, b.log_std[i]);
        return bad(format!(
            "sample {s}: log_std[{j}] = {v} is outside [ln 1e-10, 0] (sigma ~ U(0, 1))"
        ));
    }
    if let Some(i) = bounds.change_beyond(&b.delta) {
        let (s, j, v) = (i / l.aligned_dim, i % l.aligned_dim, b.delta[i]);
        return bad(format!(
            "sample {s}: delta[{j}] = {v} is beyond the env's largest step +-{}",
            bounds.max_change
        ));
    }
    let mut x = Vec::with_capacity(n * l.pcpn_input_dim());
    for i in 0..n {
        x.extend_from_slice(&b.obs[i * l.obs_dim..(i + 1) * l.obs_dim]);
        x.extend_from_slice(&b.mu[i * l.mu_dim()..(i + 1) * l.mu_dim()]);
        x.extend_from_slice(&b.log_std[i * l.log_std_dim()..(i + 1) * l.log_std_dim()]);
    }
    Ok(Samples {
        x,
        delta: b.delta.clone(),
        n,
    })
}

/// Serves one provider's `ProvideSamples` call: its first message names its env;
/// then it answers demands until it leaves, the store stops, or it sends a bad
/// sample (the stream then ends with INVALID_ARGUMENT, saying which).
pub async fn provide(
    hub: Arc<SampleHub>,
    mut inbound: tonic::Streaming<pb::SampleBatch>,
    tx: tokio::sync::mpsc::Sender<std::result::Result<pb::SampleDemand, tonic::Status>>,
) {
    use tokio_stream::StreamExt;
    let invalid = |e: &dyn std::fmt::Display| tonic::Status::invalid_argument(e.to_string());
    let spec = match inbound.next().await {
        Some(Ok(hello)) => match hello.env.as_ref().map(EnvSpec::try_from) {
            Some(Ok(spec)) if spec.kind().is_none() => spec.dynamics(),
            Some(Ok(spec)) => {
                let msg = format!("{spec} is a built-in env: the store samples it itself");
                let _ = tx.send(Err(tonic::Status::invalid_argument(msg))).await;
                return;
            }
            Some(Err(e)) => {
                let _ = tx.send(Err(invalid(&e))).await;
                return;
            }
            None => {
                let msg = "the first SampleBatch must name the env (env, n = 0)";
                let _ = tx.send(Err(tonic::Status::invalid_argument(msg))).await;
                return;
            }
        },
        _ => return,
    };
    let id = hub.join(spec.clone());
    hub.arrived.notify_all();
    let mut work = hub.work.subscribe();
    loop {
        let Some((count, received, total)) = hub.take(&spec) else {
            tokio::select! {
                changed = work.changed() => if changed.is_err() { break },
                _ = tx.closed() => break,
            }
            continue;
        };
        let demand = pb::SampleDemand {
            env: Some((&spec).into()),
            count,
            batches_done: (received / CHUNK as u64) as u32,
            batches: total.div_ceil(CHUNK as u64),
            samples_received: received,
            samples_total: total,
        };
        if tx.send(Ok(demand)).await.is_err() {
            hub.give_back(&spec, count as u64);
            break;
        }
        let mut got = 0u32;
        while got < count {
            match inbound.next().await {
                Some(Ok(b)) => match check_batch(&spec, &b, count - got) {
                    Ok(s) => {
                        got += s.n as u32;
                        hub.deliver(&spec, s);
                    }
                    Err(e) => {
                        tracing::warn!("sample provider {id}: {e}; cut off");
                        hub.give_back(&spec, (count - got) as u64);
                        let _ = tx.send(Err(invalid(&e))).await;
                        hub.leave(id);
                        return;
                    }
                },
                _ => {
                    hub.give_back(&spec, (count - got) as u64);
                    hub.leave(id);
                    tracing::info!("sample provider {id} for {spec} left");
                    return;
                }
            }
        }
    }
    hub.leave(id);
}

#[cfg(test)]
mod tests {
    use super::*;

    /// obs [x, y], one continuous action, aligned entry 0.
    fn spec() -> EnvSpec {
        EnvSpec::unit_custom("line", 0.1).unwrap()
    }

    /// `n` samples whose delta is their arrival number / 1e5 (each one recognisable).
    fn batch(from: u32, n: u32) -> pb::SampleBatch {
        pb::SampleBatch {
            env: None,
            n,
            obs: (0..n).flat_map(|_| [0.5, -0.5]).collect(),
            mu: vec![0.25; n as usize],
            log_std: vec![-1.0; n as usize],
            delta: (from..from + n).map(|i| i as f32 * 1e-5).collect(),
        }
    }

    /// A pretraining that no provider feeds fails after the deadline, saying what it
    /// waited for; samples that keep arriving keep it going.
    #[test]
    fn a_pretraining_nobody_feeds_ends_at_its_deadline() {
        let hub = Arc::new(SampleHub::with_deadline(Duration::from_millis(50)));
        let s = spec();
        let mut source = hub.source(&s, 2_000, 7).unwrap();
        hub.deliver(&s, check_batch(&s, &batch(0, 1_000), 1_000).unwrap());
        assert_eq!(source.held_out(1_000).unwrap().samples.n, 1_000);
        let e = source.held_out(1).err().unwrap().to_string();
        assert!(
            e.contains("no samples arrived")
                && e.contains("0 sample providers connected; 1000 of 2000")
                && e.contains("--pretrain-deadline"),
            "{e}"
        );
    }

    #[test]
    fn every_streamed_sample_is_used_once_and_the_first_are_held_out() {
        let hub = Arc::new(SampleHub::default());
        let s = spec();
        let (held, total) = (100usize, 5_000u32);
        let mut source = hub.source(&s, total as u64, 7).unwrap();
        // Three providers' chunks, delivered as they would arrive.
        for (from, n) in [(0, 1_000), (1_000, 2_500), (3_500, 1_500)] {
            hub.deliver(&s, check_batch(&s, &batch(from, n), n).unwrap());
        }
        let h = source.held_out(held).unwrap();
        let seen: Vec<u32> = h
            .samples
            .delta
            .iter()
            .map(|d| (d * 1e5).round() as u32)
            .collect();
        assert_eq!(seen, (0..held as u32).collect::<Vec<_>>());
        // x = [obs, mu, log sigma] for every sample.
        assert_eq!(&h.samples.x[..4], &[0.5, -0.5, 0.25, -1.0]);
        let mut drawn = Vec::new();
        while drawn.len() < total as usize - held {
            let b = source
                .sample(128.min(total as usize - held - drawn.len()))
                .unwrap();
            drawn.extend(b.delta.iter().map(|d| (d * 1e5).round() as u32));
        }
        // Shuffled (not in arrival order), yet each of the rest exactly once.
        assert_ne!(
            drawn[..50],
            (held as u32..held as u32 + 50).collect::<Vec<_>>()[..]
        );
        drawn.sort_unstable();
        assert_eq!(drawn, (held as u32..total).collect::<Vec<_>>());
        assert!(source.sample(1).is_err(), "more than announced");
    }

    /// walk_samples: the held-out rows first, then a pool of the next 1,000 that
    /// batches draw from with replacement (every draw one of those 1,000, none of the
    /// held-out ones, and with 20,000 draws nearly all of them: the chance that one row
    /// is never drawn is (1 - 1/1000)^20000 = e^-20, so all 1,000 appear), and the
    /// held-out replay serves its rows in order, again from the start.
    #[test]
    fn a_pool_draws_its_rows_with_replacement() {
        let hub = Arc::new(SampleHub::default());
        let s = spec();
        let mut source = hub.source(&s, 1_100, 7).unwrap();
        hub.deliver(&s, check_batch(&s, &batch(0, 1_100), 1_100).unwrap());
        let mut held = source.held_out(100).unwrap();
        let mut pool = source.into_pool(1_000).unwrap();
        let ids =
            |b: Samples| -> Vec<u32> { b.delta.iter().map(|d| (d * 1e5).round() as u32).collect() };
        let mut drawn: Vec<u32> = (0..20)
            .flat_map(|_| ids(pool.sample(1_000).unwrap()))
            .collect();
        assert_eq!(drawn.len(), 20_000);
        assert!(
            drawn.iter().all(|i| (100..1_100).contains(i)),
            "only pool rows"
        );
        drawn.sort_unstable();
        drawn.dedup();
        assert_eq!(drawn.len(), 1_000, "every pool row drawn");
        let first = ids(held.sample(60).unwrap());
        let again = ids(held.sample(60).unwrap());
        assert_eq!(first, (0..60).collect::<Vec<_>>());
        assert_eq!(again, (60..100).chain(0..20).collect::<Vec<_>>());
    }

    #[test]
    fn bad_samples_are_refused_by_what_is_wrong() {
        let s = spec();
        type Spoil = Box<dyn Fn(&mut pb::SampleBatch)>;
        let cases: Vec<(Spoil, &str)> = vec![
            (
                Box::new(|b| b.obs[3] = 1.5),
                "sample 1: observation entry 1 = 1.5 is outside",
            ),
            (
                Box::new(|b| b.mu[0] = -1.2),
                "mu[0] = -1.2 is outside [-1, 1]",
            ),
            (Box::new(|b| b.log_std[2] = 0.5), "log_std[0] = 0.5"),
            (
                Box::new(|b| b.delta[1] = 0.2),
                "delta[0] = 0.2 is beyond the env's largest step",
            ),
            (Box::new(|b| b.delta[0] = f32::NAN), "delta[0] = NaN"),
            (
                Box::new(|b| b.obs.pop().map(|_| ()).unwrap_or(())),
                "obs has 7 values, not n x 2 = 8",
            ),
            (
                Box::new(|b| b.n = 9),
                "n = 9 where 1..=4 samples are still owed",
            ),
        ];
        for (spoil, want) in cases {
            let mut b = batch(0, 4);
            spoil(&mut b);
            let err = check_batch(&s, &b, 4).err().unwrap().to_string();
            assert!(err.contains(want), "{want:?} not in {err:?}");
        }
        assert_eq!(check_batch(&s, &batch(0, 4), 4).unwrap().n, 4);
    }
}

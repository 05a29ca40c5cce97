//! Run metrics: the mean length of the last 100 finished episodes (over all actors and
//! over actor 0 alone, as the paper plotted), and metrics.csv, one row per update.

use saver_core::rollout::Episode;
use saver_proto::NamedTensor;
use std::collections::VecDeque;
use std::io::Write;
use std::path::Path;

/// Episodes the running mean covers (the paper's 100).
pub const WINDOW: usize = 100;

/// The last [`WINDOW`] episode lengths, over all actors and for actor 0.
#[derive(Clone, Debug, Default)]
pub struct EpisodeWindow {
    /// All actors.
    all: VecDeque<u32>,
    /// Actor 0 only.
    actor0: VecDeque<u32>,
    /// Episodes seen in total.
    pub total: u64,
    /// Of those, reached the goal.
    pub successes: u64,
}

fn push(q: &mut VecDeque<u32>, x: u32) {
    if q.len() == WINDOW {
        q.pop_front();
    }
    q.push_back(x);
}

fn mean(q: &VecDeque<u32>) -> Option<f64> {
    (!q.is_empty()).then(|| q.iter().map(|&x| x as f64).sum::<f64>() / q.len() as f64)
}

impl EpisodeWindow {
    /// Adds finished episodes (only verified ones: see [`Episode::verified`]).
    pub fn extend(&mut self, episodes: &[Episode]) {
        for e in episodes.iter().filter(|e| e.verified) {
            push(&mut self.all, e.length);
            if e.actor_id == 0 {
                push(&mut self.actor0, e.length);
            }
            self.total += 1;
            self.successes += e.success as u64;
        }
    }
    /// Mean of the last 100 over all actors (None before the first episode).
    pub fn mean_all(&self) -> Option<f64> {
        mean(&self.all)
    }
    /// Mean of actor 0's last 100.
    pub fn mean_actor0(&self) -> Option<f64> {
        mean(&self.actor0)
    }

    /// The two windows as tensors `window.all` and `window.actor0` (lengths are exact
    /// in f32 below 2^24), for a checkpoint; the totals go in its metadata.
    pub fn to_saved(&self) -> Vec<NamedTensor> {
        [("window.all", &self.all), ("window.actor0", &self.actor0)]
            .into_iter()
            .map(|(name, q)| NamedTensor {
                name: name.into(),
                shape: vec![q.len()],
                data: q.iter().map(|&x| x as f32).collect(),
            })
            .collect()
    }

    /// Inverse of [`EpisodeWindow::to_saved`]; missing tensors are empty windows, and
    /// values that are no episode length are left out.
    pub fn from_saved(
        all: Option<&NamedTensor>,
        actor0: Option<&NamedTensor>,
        total: u64,
        successes: u64,
    ) -> Self {
        let q = |t: Option<&NamedTensor>| -> VecDeque<u32> {
            let lengths = t.map_or(&[][..], |t| &t.data);
            let mut q: VecDeque<u32> = lengths
                .iter()
                .filter(|x| x.is_finite() && **x >= 1.0 && **x < 16_777_216.0)
                .map(|&x| x as u32)
                .collect();
            q.drain(..q.len().saturating_sub(WINDOW));
            q
        };
        Self {
            all: q(all),
            actor0: q(actor0),
            total,
            successes,
        }
    }
}

/// The hub's counts at an update, for the gauges ([`export`]); the hub fills it
/// (`Hub::counts`), so that metrics reads values, not the hub.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct HubCounts {
    /// Actors streaming rollouts.
    pub streaming: usize,
    /// Actors registered and waiting for their first weights.
    pub pending: usize,
    /// Rollouts accepted so far.
    pub accepted: u64,
    /// Rollouts refused so far.
    pub rejected: u64,
}

/// Sets the Prometheus gauges of one update (`scalars`: the update's TensorBoard
/// scalars) and of the hub (actors streaming and waiting, rollouts accepted and
/// refused).
pub fn export(scalars: &[(&'static str, f32)], row: &MetricsRow, hub: HubCounts) {
    ::metrics::gauge!("saver_steps").set(row.steps as f64);
    ::metrics::gauge!("saver_version").set(row.updates as f64);
    for &(name, value) in scalars {
        ::metrics::gauge!("saver_update_value", "name" => name).set(value as f64);
    }
    ::metrics::gauge!("saver_actors_streaming").set(hub.streaming as f64);
    ::metrics::gauge!("saver_actors_pending").set(hub.pending as f64);
    ::metrics::gauge!("saver_rollouts_accepted").set(hub.accepted as f64);
    ::metrics::gauge!("saver_rollouts_rejected").set(hub.rejected as f64);
}

/// One row of metrics.csv.
#[derive(Clone, Debug)]
pub struct MetricsRow {
    /// Env steps trained on.
    pub steps: u64,
    /// Updates (= weights version).
    pub updates: u64,
    /// Seconds since training started.
    pub wall_s: f64,
    /// steps / wall_s.
    pub steps_per_s: f64,
    /// Mean length of the last 100 episodes, all actors.
    pub mean_ep_len_100: Option<f64>,
    /// The same for actor 0.
    pub mean_ep_len_100_actor0: Option<f64>,
    /// Episodes finished so far.
    pub episodes: u64,
    /// Mean policy lag of this update's rollouts (0 in sync mode).
    pub lag_mean: f64,
    /// Largest policy lag of this update's rollouts.
    pub lag_max: u64,
    /// Rollouts dropped so far for being too stale (or duplicates).
    pub stale_dropped: u64,
    /// Updates skipped so far by this process for a non-finite loss or gradient.
    pub skipped_updates: u64,
    /// The algorithm's losses and diagnostics.
    pub stats: Vec<f32>,
}

/// Writes metrics.csv (header from the algorithm's stat names).
pub struct MetricsCsv {
    /// The open file.
    out: std::io::BufWriter<std::fs::File>,
}

fn opt(x: Option<f64>) -> String {
    x.map(|v| format!("{v:.3}")).unwrap_or_default()
}

impl MetricsCsv {
    /// Creates `path` and writes the header; with `append`, an existing file (a
    /// resumed run, see [`truncate_after`]) keeps its rows and gets the new ones after
    /// them.
    pub fn create(path: &Path, stat_names: &[&str], append: bool) -> std::io::Result<Self> {
        if append && path.exists() {
            let file = std::fs::OpenOptions::new().append(true).open(path)?;
            return Ok(Self {
                out: std::io::BufWriter::new(file),
            });
        }
        let mut out = std::io::BufWriter::new(std::fs::File::create(path)?);
        write!(
            out,
            "steps,updates,wall_s,steps_per_s,mean_ep_len_100,mean_ep_len_100_actor0,episodes,\
             lag_mean,lag_max,stale_dropped,skipped_updates"
        )?;
        for n in stat_names {
            write!(out, ",{n}")?;
        }
        writeln!(out)?;
        Ok(Self { out })
    }

    /// Appends a row (flushed, so a crash loses at most the row being written).
    pub fn write(&mut self, r: &MetricsRow) -> std::io::Result<()> {
        write!(
            self.out,
            "{},{},{:.3},{:.1},{},{},{},{:.2},{},{},{}",
            r.steps,
            r.updates,
            r.wall_s,
            r.steps_per_s,
            opt(r.mean_ep_len_100),
            opt(r.mean_ep_len_100_actor0),
            r.episodes,
            r.lag_mean,
            r.lag_max,
            r.stale_dropped,
            r.skipped_updates
        )?;
        for v in &r.stats {
            write!(self.out, ",{v:e}")?;
        }
        writeln!(self.out)?;
        self.out.flush()
    }
}

/// Writes per_dim.csv: `steps,updates` and, for each per-dimension statistic of the
/// algorithm (`UpdateStats::per_dim`), one column per dimension (`critic_mse_0`, ...),
/// each the mean over the last `every` updates (the row's steps are the last one's).
/// Nothing is written for an algorithm without such statistics.
pub struct PerDimCsv {
    /// The file.
    path: std::path::PathBuf,
    /// Keep an existing file's rows (a resumed run).
    append: bool,
    /// Updates per row.
    every: u64,
    /// The open file, once the first row is due.
    out: Option<std::io::BufWriter<std::fs::File>>,
    /// Sums since the last row, by statistic.
    sums: Vec<(&'static str, Vec<f64>)>,
    /// Updates since the last row.
    n: u64,
}

impl PerDimCsv {
    /// A writer of `path` (created at the first row).
    pub fn new(path: &Path, append: bool, every: u64) -> Self {
        Self {
            path: path.to_path_buf(),
            append,
            every: every.max(1),
            out: None,
            sums: Vec::new(),
            n: 0,
        }
    }

    /// Adds one update's statistics; writes a row every `every` updates.
    pub fn add(
        &mut self,
        steps: u64,
        updates: u64,
        stats: &[(&'static str, Vec<f32>)],
    ) -> std::io::Result<()> {
        if stats.is_empty() {
            return Ok(());
        }
        if self.sums.is_empty() {
            self.sums = stats
                .iter()
                .map(|(n, v)| (*n, vec![0.0; v.len()]))
                .collect();
        }
        for ((_, acc), (_, v)) in self.sums.iter_mut().zip(stats) {
            for (a, &x) in acc.iter_mut().zip(v) {
                *a += x as f64;
            }
        }
        self.n += 1;
        if self.n < self.every {
            return Ok(());
        }
        if self.out.is_none() {
            let existing = self.append && self.path.exists();
            let file = std::fs::OpenOptions::new()
                .create(true)
                .append(existing)
                .write(true)
                .truncate(!existing)
                .open(&self.path)?;
            let mut out = std::io::BufWriter::new(file);
            if !existing {
                write!(out, "steps,updates")?;
                for (name, v) in &self.sums {
                    for i in 0..v.len() {
                        write!(out, ",{name}_{i}")?;
                    }
                }
                writeln!(out)?;
            }
            self.out = Some(out);
        }
        let n = self.n as f64;
        let Some(out) = self.out.as_mut() else {
            return Ok(());
        };
        write!(out, "{steps},{updates}")?;
        for (_, acc) in &mut self.sums {
            for a in acc.iter_mut() {
                write!(out, ",{:e}", (*a / n) as f32)?;
                *a = 0.0;
            }
        }
        writeln!(out)?;
        self.n = 0;
        out.flush()
    }
}

/// A resumed run's metrics.csv: drops the rows written after its checkpoint (more
/// than `steps` steps: the run goes on from the checkpoint and writes them anew) and
/// returns how many it dropped and the largest weights version any row names (every
/// published version has its row: the row is written before the version is
/// published). A missing file is no rows.
pub fn truncate_after(path: &Path, steps: u64) -> std::io::Result<(usize, u64)> {
    let text = match std::fs::read_to_string(path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok((0, 0)),
        Err(e) => return Err(e),
    };
    let mut keep = String::with_capacity(text.len());
    let (mut dropped, mut max_version) = (0, 0);
    for (i, line) in text.lines().enumerate() {
        let mut cols = line.split(',');
        let row_steps = cols.next().and_then(|v| v.parse::<u64>().ok());
        let version = cols.next().and_then(|v| v.parse::<u64>().ok());
        // The header, and rows of the run up to its checkpoint; a half-written last row
        // (a kill while writing) goes too.
        match (i, row_steps, version) {
            (0, _, _) => {}
            (_, Some(s), Some(v)) if s <= steps => max_version = max_version.max(v),
            (_, _, v) => {
                max_version = max_version.max(v.unwrap_or(0));
                dropped += 1;
                continue;
            }
        }
        keep.push_str(line);
        keep.push('\n');
    }
    if dropped > 0 {
        let tmp = path.with_extension("csv.tmp");
        std::fs::write(&tmp, keep)?;
        std::fs::rename(&tmp, path)?;
    }
    Ok((dropped, max_version))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn window_keeps_the_last_hundred_and_actor_zero_apart() {
        let mut w = EpisodeWindow::default();
        assert_eq!(w.mean_all(), None);
        // 150 episodes of actor 1 with length 10, then 100 of actor 0 with length 30:
        // the all-actor window holds only the last 100 (all 30s); actor 0's mean is 30.
        let ep = |actor_id, length| Episode {
            actor_id,
            length,
            success: true,
            ret: 0.0,
            verified: true,
        };
        w.extend(&vec![ep(1, 10); 150]);
        assert_eq!(w.mean_all(), Some(10.0));
        assert_eq!(w.mean_actor0(), None);
        w.extend(&vec![ep(0, 30); 50]);
        // Last 100: 50 tens and 50 thirties → 20.
        assert_eq!(w.mean_all(), Some(20.0));
        assert_eq!(w.mean_actor0(), Some(30.0));
        assert_eq!(w.total, 200);
        // Through a checkpoint and back: the same means.
        let saved = w.to_saved();
        let back = EpisodeWindow::from_saved(saved.first(), saved.get(1), w.total, w.successes);
        assert_eq!(back.mean_all(), Some(20.0));
        assert_eq!(back.mean_actor0(), Some(30.0));
        assert_eq!(back.total, 200);
    }

    #[test]
    fn a_resumed_csv_loses_the_rows_after_its_checkpoint_and_names_the_last_version() {
        let dir = std::env::temp_dir().join(format!("saver-csv-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("metrics.csv");
        // Checkpoint at 200 steps; rows at 300 and 400 (versions 3, 4) came after it,
        // and a row cut off by a kill.
        std::fs::write(
            &path,
            "steps,updates,x\n100,1,a\n200,2,b\n300,3,c\n400,4,d\n50",
        )
        .unwrap();
        assert_eq!(truncate_after(&path, 200).unwrap(), (3, 4));
        assert_eq!(
            std::fs::read_to_string(&path).unwrap(),
            "steps,updates,x\n100,1,a\n200,2,b\n"
        );
        assert_eq!(truncate_after(&dir.join("none.csv"), 0).unwrap(), (0, 0));
        std::fs::remove_dir_all(dir).ok();
    }

    #[test]
    fn per_dim_rows_are_means_over_every_updates() {
        let dir = std::env::temp_dir().join(format!("saver-perdim-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("per_dim.csv");
        let mut w = PerDimCsv::new(&path, false, 2);
        // Means of (1, 3) and (10, 30) over 2 updates: 2 and 20; (5, 7) -> 6, ...
        for (s, a, b) in [
            (8, 1.0, 10.0),
            (16, 3.0, 30.0),
            (24, 5.0, 50.0),
            (32, 7.0, 70.0),
        ] {
            w.add(s, s / 8, &[("critic_mse", vec![a, b]), ("mu_sat", vec![a])])
                .unwrap();
        }
        let text = std::fs::read_to_string(&path).unwrap();
        assert_eq!(
            text,
            "steps,updates,critic_mse_0,critic_mse_1,mu_sat_0\n16,2,2e0,2e1,2e0\n32,4,6e0,6e1,6e0\n"
        );
        // A resumed run appends below the kept rows, without a second header.
        let mut w = PerDimCsv::new(&path, true, 1);
        w.add(
            40,
            5,
            &[("critic_mse", vec![1.0, 2.0]), ("mu_sat", vec![0.5])],
        )
        .unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(
            text.ends_with("32,4,6e0,6e1,6e0\n40,5,1e0,2e0,5e-1\n"),
            "{text}"
        );
        // An algorithm without per-dimension statistics writes no file.
        let none = dir.join("none.csv");
        PerDimCsv::new(&none, false, 1).add(8, 1, &[]).unwrap();
        assert!(!none.exists());
        std::fs::remove_dir_all(&dir).ok();
    }
}

//! Where each update's numbers go: metrics.csv, per_dim.csv, the TensorBoard event
//! file, the Prometheus gauges and, for a progress display, a channel of rows. The
//! trainer hands each update's row to [`Sinks::write`] once.

use crate::metrics::{export, HubCounts, MetricsCsv, MetricsRow, PerDimCsv};
use crate::tensorboard::{hparams_of, scalars, EventWriter};
use saver_core::algo::UpdateStats;
use saver_core::config::RunConfig;
use saver_core::rollout::Episode;
use saver_core::{CoreError, Result};
use std::path::Path;
use std::sync::mpsc::Sender;

/// Updates per row of per_dim.csv (each row the mean over them).
const PER_DIM_EVERY: u64 = 10;

/// An I/O error of a run folder file, as the run reports it.
pub(crate) fn io_error(what: &str, e: std::io::Error) -> CoreError {
    CoreError::Checkpoint(format!("{what}: {e}"))
}

/// The run's outputs of per-update numbers.
pub(crate) struct Sinks {
    csv: MetricsCsv,
    per_dim: PerDimCsv,
    events: EventWriter,
    rows: Option<Sender<MetricsRow>>,
    /// The algorithm's stat names, in the columns' order.
    stat_names: Vec<&'static str>,
}

impl Sinks {
    /// Opens them in `run_dir` (appending where a resumed run left them), with the
    /// run's settings as TensorBoard hparams.
    pub(crate) fn open(
        run_dir: &Path,
        stat_names: Vec<&'static str>,
        resumed: bool,
        config: &RunConfig,
        rows: Option<Sender<MetricsRow>>,
    ) -> Result<Self> {
        let csv = MetricsCsv::create(&run_dir.join("metrics.csv"), &stat_names, resumed)
            .map_err(|e| io_error("creating metrics.csv", e))?;
        let per_dim = PerDimCsv::new(&run_dir.join("per_dim.csv"), resumed, PER_DIM_EVERY);
        let mut events = EventWriter::create(run_dir)
            .map_err(|e| io_error("creating the TensorBoard event file", e))?;
        events
            .write_hparams(&hparams_of(
                &serde_json::to_value(config).unwrap_or_default(),
            ))
            .map_err(|e| io_error("writing the TensorBoard hparams", e))?;
        Ok(Self {
            csv,
            per_dim,
            events,
            rows,
            stat_names,
        })
    }

    /// The stats of an update in the columns' order, by name (NaN for a value not
    /// reported).
    pub(crate) fn columns(&self, stats: &UpdateStats) -> Vec<f32> {
        self.stat_names
            .iter()
            .map(|n| stats.get(n).unwrap_or(f32::NAN))
            .collect()
    }

    /// Writes one update's row everywhere; `episodes` ended in its batch.
    pub(crate) fn write(
        &mut self,
        row: MetricsRow,
        stats: &UpdateStats,
        episodes: &[Episode],
        hub: HubCounts,
    ) -> Result<()> {
        // The row before the version: a resumed run learns from metrics.csv the
        // newest version any client can have seen.
        self.csv
            .write(&row)
            .map_err(|e| io_error("writing metrics.csv", e))?;
        self.per_dim
            .add(row.steps, row.updates, &stats.per_dim)
            .map_err(|e| io_error("writing per_dim.csv", e))?;
        let scalars = scalars(&row, &self.stat_names, episodes);
        self.events
            .write(row.steps, &scalars)
            .map_err(|e| io_error("writing the TensorBoard events", e))?;
        export(&scalars, &row, hub);
        if let Some(tx) = &self.rows {
            let _ = tx.send(row);
        }
        Ok(())
    }
}

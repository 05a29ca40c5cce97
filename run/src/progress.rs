//! Progress of long work: an indicatif bar on a terminal, a plain line every few
//! seconds otherwise (logs, CI), so a run always shows that it moves.

use indicatif::{ProgressBar, ProgressStyle};
use std::io::IsTerminal;
use std::time::{Duration, Instant};

/// Seconds between plain progress lines when stderr is not a terminal.
const LINE_EVERY: Duration = Duration::from_secs(10);

/// A progress display.
pub struct Progress {
    /// The bar, on a terminal.
    bar: Option<ProgressBar>,
    /// What is counted.
    label: String,
    /// Total count.
    total: u64,
    /// Unit of the count ("steps", "batches").
    unit: &'static str,
    /// When the plain line was last printed.
    last_line: Instant,
    /// Start time and position (rates; a resumed run starts past 0).
    start: Option<(Instant, u64)>,
}

impl Progress {
    /// A display for `total` units.
    pub fn new(label: &str, total: u64, unit: &'static str) -> Self {
        let bar = std::io::stderr().is_terminal().then(|| {
            let b = ProgressBar::new(total);
            let style = ProgressStyle::with_template(&format!(
                "{{prefix}} [{{elapsed_precise}}] {{wide_bar}} {{human_pos}}/{{human_len}} {unit} \
                 {{per_sec}} eta {{eta}} {{msg}}"
            ))
            .unwrap_or_else(|_| ProgressStyle::default_bar());
            b.set_style(style);
            b.set_prefix(label.to_string());
            b.enable_steady_tick(Duration::from_millis(250));
            b
        });
        Self {
            bar,
            label: label.to_string(),
            total,
            unit,
            last_line: Instant::now(),
            start: None,
        }
    }

    /// Moves to `pos` with a status message.
    pub fn update(&mut self, pos: u64, msg: &str) {
        let (t0, pos0) = *self.start.get_or_insert((Instant::now(), pos));
        match &self.bar {
            Some(b) => {
                b.set_position(pos);
                b.set_message(msg.to_string());
            }
            None if self.last_line.elapsed() >= LINE_EVERY => {
                self.last_line = Instant::now();
                let rate = pos.saturating_sub(pos0) as f64 / t0.elapsed().as_secs_f64().max(1e-9);
                eprintln!(
                    "{}: {pos}/{} {} ({rate:.0}/s) {msg}",
                    self.label, self.total, self.unit
                );
            }
            None => {}
        }
    }

    /// Ends the display.
    pub fn finish(&self) {
        if let Some(b) = &self.bar {
            b.finish();
        }
    }
}

//! `saver plot` and the run folder's learning curve: reading metrics.csv and the
//! command; the drawing is figures.rs.

use anyhow::{bail, Context, Result};
use clap::Args;
use plotters::style::FontStyle;
use std::path::{Path, PathBuf};
use std::sync::Once;

/// `saver plot` flags.
#[derive(Args, Clone, Debug)]
pub struct PlotArgs {
    /// Run folders (each with config.toml and metrics.csv); runs that differ only in
    /// their seed are drawn as one mean with a band of one standard deviation.
    #[arg(required = true)]
    pub runs: Vec<PathBuf>,
    /// Output image: PNG, or SVG when the name ends in .svg. The table goes next to it
    /// (same name, .md).
    #[arg(long, default_value = "learning_curves.png")]
    pub out: PathBuf,
    /// Table: the mean episode length at these steps.
    #[arg(long, value_delimiter = ',', default_value = "500000,1000000,2560000")]
    pub at: Vec<u64>,
    /// Table: steps until the mean length first falls below this.
    #[arg(long, default_value_t = 50.0)]
    pub threshold: f64,
}

/// Runs `saver plot`: the grouped figure and its table.
pub fn run(args: PlotArgs) -> Result<()> {
    let groups = crate::figures::group(&args.runs)?;
    crate::figures::draw(&groups, &args.out)?;
    let table = crate::figures::table(&groups, &args.at, args.threshold);
    let md = args.out.with_extension("md");
    std::fs::write(&md, &table).with_context(|| format!("writing {}", md.display()))?;
    crate::out!("{table}");
    crate::out!(
        "Figure written to {}, table to {}",
        args.out.display(),
        md.display()
    );
    Ok(())
}

/// (steps, mean episode length) points of a run's metrics.csv, from the row where
/// 100 episodes have finished (before it the "last 100 episodes" are a few short
/// ones, which would put a curve below any threshold by chance).
pub fn read_curve(run: &Path) -> Result<Vec<(f64, f64)>> {
    let path = run.join("metrics.csv");
    let text =
        std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap_or_default().split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name);
    let (Some(s), Some(m)) = (col("steps"), col("mean_ep_len_100")) else {
        bail!("{}: no steps / mean_ep_len_100 columns", path.display());
    };
    let episodes = col("episodes");
    let mut points = Vec::new();
    for line in lines {
        let f: Vec<&str> = line.split(',').collect();
        let full = episodes
            .and_then(|e| f.get(e)?.parse::<u64>().ok())
            .is_none_or(|n| n >= 100);
        if let (true, Some(Ok(x)), Some(Ok(y))) = (
            full,
            f.get(s).map(|v| v.parse()),
            f.get(m).map(|v| v.parse()),
        ) {
            points.push((x, y));
        }
    }
    Ok(points)
}

pub(crate) fn register_font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        let _ = plotters::style::register_font(
            "sans-serif",
            FontStyle::Normal,
            dejavu::sans::regular(),
        );
    });
}

/// Draws the runs' curves into `png` (as `saver plot` does: seeds of one setting
/// grouped, one panel per env).
pub fn plot_runs(runs: &[PathBuf], png: &Path) -> Result<()> {
    crate::figures::draw(&crate::figures::group(runs)?, png)
}

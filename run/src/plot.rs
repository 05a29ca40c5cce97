//! `saver plot` and the run folder's learning curve: the command; reading metrics.csv
//! and the drawing are figures.rs.

use anyhow::{Context, Result};
use clap::Args;
use std::path::{Path, PathBuf};

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

/// Draws the runs' curves into `png` (as `saver plot` does: seeds of one setting
/// grouped, one panel per env).
pub fn plot_runs(runs: &[PathBuf], png: &Path) -> Result<()> {
    crate::figures::draw(&crate::figures::group(runs)?, png)
}

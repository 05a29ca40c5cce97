//! Learning curves like the paper's figures: mean length of the last 100 episodes
//! against training steps (millions), one line per run folder.

use anyhow::{bail, Context, Result};
use clap::Args;
use plotters::prelude::*;
use std::path::{Path, PathBuf};
use std::sync::Once;

/// `saver plot` flags.
#[derive(Args, Clone, Debug)]
pub struct PlotArgs {
    /// Run folders (each with a metrics.csv).
    #[arg(required = true)]
    pub runs: Vec<PathBuf>,
    /// Output PNG.
    #[arg(long, default_value = "learning_curves.png")]
    pub out: PathBuf,
}

/// Runs `saver plot`.
pub fn run(args: PlotArgs) -> Result<()> {
    plot_runs(&args.runs, &args.out)?;
    crate::out!("Plot written to {}", args.out.display());
    Ok(())
}

/// (steps, mean episode length) points of a run's metrics.csv.
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
    let mut points = Vec::new();
    for line in lines {
        let f: Vec<&str> = line.split(',').collect();
        if let (Some(Ok(x)), Some(Ok(y))) =
            (f.get(s).map(|v| v.parse()), f.get(m).map(|v| v.parse()))
        {
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

/// Draws the runs' curves into `png`.
pub fn plot_runs(runs: &[PathBuf], png: &Path) -> Result<()> {
    register_font();
    let curves: Vec<(String, Vec<(f64, f64)>)> = runs
        .iter()
        .map(|r| {
            let name = r
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            read_curve(r).map(|c| (name, c))
        })
        .collect::<Result<_>>()?;
    let max_x = curves
        .iter()
        .flat_map(|(_, c)| c.iter().map(|p| p.0))
        .fold(1.0, f64::max)
        / 1e6;
    let max_y = curves
        .iter()
        .flat_map(|(_, c)| c.iter().map(|p| p.1))
        .fold(10.0, f64::max)
        * 1.05;
    let root = BitMapBackend::new(png, (900, 560)).into_drawing_area();
    root.fill(&WHITE)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(
            "mean episode length (last 100 episodes)",
            ("sans-serif", 22),
        )
        .margin(12)
        .x_label_area_size(45)
        .y_label_area_size(60)
        .build_cartesian_2d(0.0..max_x, 0.0..max_y)?;
    chart
        .configure_mesh()
        .x_desc("training steps (millions)")
        .y_desc("episode length")
        .label_style(("sans-serif", 14))
        .draw()?;
    for (i, (name, c)) in curves.iter().enumerate() {
        let color = Palette99::pick(i).to_rgba();
        chart
            .draw_series(LineSeries::new(
                c.iter().map(|&(x, y)| (x / 1e6, y)),
                color.stroke_width(2),
            ))?
            .label(name.clone())
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2))
            });
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .label_font(("sans-serif", 14))
        .draw()?;
    root.present()
        .with_context(|| format!("writing {}", png.display()))?;
    Ok(())
}

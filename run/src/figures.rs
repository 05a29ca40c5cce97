//! Figures like the paper's from any set of run folders: runs that differ only in
//! their seed form a group, drawn as the mean over seeds of the mean length of the last
//! 100 episodes against steps with a band of one standard deviation, one panel per env;
//! and a table per group (length at fixed steps, steps until the mean first falls below
//! a threshold, final length; mean +/- std over seeds). PNG or SVG by the file name.

use anyhow::{bail, Context, Result};
use plotters::coord::Shift;
use plotters::prelude::*;
use saver_core::config::RunConfig;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Once;

/// Points on the common step grid of a group.
const GRID: usize = 200;

/// (step, mean, standard deviation) over a group's seeds.
pub type Band = Vec<(f64, f64, f64)>;

/// Runs that differ only in their seed.
pub struct Group {
    /// What the runs are: algorithm, env and what sets the group apart.
    pub label: String,
    /// The label without the env: a series keeps its colour across panels.
    pub series: String,
    /// The env (one panel per env).
    pub env: String,
    /// One per seed.
    pub runs: Vec<Run>,
}

/// One run folder of a group.
pub struct Run {
    /// The folder.
    pub dir: PathBuf,
    /// Its config.toml.
    pub config: RunConfig,
    /// Its curve (steps, mean length of the last 100 episodes).
    pub curve: Vec<(f64, f64)>,
}

/// The run folders grouped by their settings but the seed (and the run's length),
/// each labelled with what sets it apart ([`crate::labels::series`]).
pub fn group(runs: &[PathBuf]) -> Result<Vec<Group>> {
    let mut groups: BTreeMap<String, Vec<Run>> = BTreeMap::new();
    for run in runs {
        let cfg = run.join("config.toml");
        let text =
            std::fs::read_to_string(&cfg).with_context(|| format!("reading {}", cfg.display()))?;
        let config =
            RunConfig::from_toml(&text).with_context(|| format!("reading {}", cfg.display()))?;
        let key = RunConfig {
            seed: 0,
            steps: 0,
            pcpn_sha256: None,
            ..config.clone()
        }
        .to_toml();
        let curve = read_curve(run)?;
        groups.entry(key).or_default().push(Run {
            dir: run.clone(),
            config,
            curve,
        });
    }
    let configs: Vec<&RunConfig> = groups.values().map(|r| &r[0].config).collect();
    let names = crate::labels::series(&configs);
    let mut out: Vec<Group> = groups
        .into_values()
        .zip(names)
        .map(|(runs, series)| {
            let env = runs[0].config.env.to_string();
            Group {
                label: format!("{series} {env}"),
                series,
                env,
                runs,
            }
        })
        .collect();
    out.sort_by(|a, b| (&a.env, &a.label).cmp(&(&b.env, &b.label)));
    // Labels that would repeat get a number.
    for i in 1..out.len() {
        if out[..i].iter().any(|g| g.label == out[i].label) {
            out[i].label = format!("{} #{}", out[i].label, i + 1);
            out[i].series = format!("{} #{}", out[i].series, i + 1);
        }
    }
    Ok(out)
}

/// The group's mean and standard deviation over seeds on a step grid up to the
/// shortest run's last step; a seed counts at a step once its curve has begun.
pub fn band(g: &Group) -> Band {
    let end = g
        .runs
        .iter()
        .map(|r| r.curve.last().map_or(0.0, |p| p.0))
        .fold(f64::INFINITY, f64::min);
    if !end.is_finite() || end <= 0.0 {
        return Vec::new();
    }
    (1..=GRID)
        .filter_map(|i| {
            let x = end * i as f64 / GRID as f64;
            let ys: Vec<f64> = g.runs.iter().filter_map(|r| at(&r.curve, x)).collect();
            if ys.is_empty() {
                return None;
            }
            let m = ys.iter().sum::<f64>() / ys.len() as f64;
            let var = ys.iter().map(|y| (y - m).powi(2)).sum::<f64>() / ys.len() as f64;
            Some((x, m, var.sqrt()))
        })
        .collect()
}

/// The curve's value at step `x`: the last point at or before it.
fn at(c: &[(f64, f64)], x: f64) -> Option<f64> {
    let i = c.partition_point(|p| p.0 <= x);
    (i > 0).then(|| c[i - 1].1)
}

/// Mean and standard deviation of `v` (population).
fn mean_std(v: &[f64]) -> (f64, f64) {
    let m = v.iter().sum::<f64>() / v.len() as f64;
    let s = (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / v.len() as f64).sqrt();
    (m, s)
}

/// A markdown table: each group's mean length at `steps`, the steps until its curve
/// first falls below `threshold`, and its final length; mean +/- std over seeds (a
/// seed that never falls below the threshold is counted in "never").
pub fn table(groups: &[Group], steps: &[u64], threshold: f64) -> String {
    let mut t = format!(
        "| group | seeds |{} steps to < {threshold} | final |\n|---|---|{}---|---|\n",
        steps
            .iter()
            .map(|s| format!(" at {} |", human(*s)))
            .collect::<String>(),
        steps.iter().map(|_| "---|").collect::<String>()
    );
    for g in groups {
        let mut row = format!("| {} | {} |", g.label, g.runs.len());
        for &s in steps {
            let v: Vec<f64> = g
                .runs
                .iter()
                .filter_map(|r| at(&r.curve, s as f64))
                .collect();
            row.push_str(&if v.len() == g.runs.len() {
                let (m, sd) = mean_std(&v);
                format!(" {m:.1} +/- {sd:.1} |")
            } else {
                " - |".to_string()
            });
        }
        let firsts: Vec<Option<f64>> = g
            .runs
            .iter()
            .map(|r| r.curve.iter().find(|p| p.1 < threshold).map(|p| p.0))
            .collect();
        let reached: Vec<f64> = firsts.iter().flatten().copied().collect();
        let never = firsts.len() - reached.len();
        row.push_str(&match (reached.is_empty(), never) {
            (true, _) => " never |".to_string(),
            (false, 0) => {
                let (m, sd) = mean_std(&reached);
                format!(" {} +/- {} |", human(m as u64), human(sd as u64))
            }
            (false, n) => {
                let (m, sd) = mean_std(&reached);
                format!(
                    " {} +/- {} ({n} never) |",
                    human(m as u64),
                    human(sd as u64)
                )
            }
        });
        let finals: Vec<f64> = g
            .runs
            .iter()
            .filter_map(|r| r.curve.last().map(|p| p.1))
            .collect();
        row.push_str(&if finals.len() < g.runs.len() {
            " - (a seed has fewer than 100 episodes) |\n".to_string()
        } else {
            let (m, sd) = mean_std(&finals);
            format!(" {m:.1} +/- {sd:.1} |\n")
        });
        t.push_str(&row);
    }
    t
}

/// 2560000 -> "2.56M", 81000 -> "81k".
fn human(s: u64) -> String {
    if s >= 1_000_000 {
        format!("{}M", (s as f64 / 1e6 * 100.0).round() / 100.0)
    } else if s >= 1_000 {
        format!("{}k", (s as f64 / 1e3).round())
    } else {
        s.to_string()
    }
}

/// Draws the groups, one panel per env, into `out` (SVG when it ends in .svg, else PNG).
pub fn draw(groups: &[Group], out: &Path) -> Result<()> {
    let envs: Vec<&str> = {
        let mut e: Vec<&str> = groups.iter().map(|g| g.env.as_str()).collect();
        e.dedup();
        e
    };
    if envs.is_empty() {
        bail!("no runs to draw");
    }
    let cols = envs.len().min(2);
    let rows = envs.len().div_ceil(cols);
    let size = (560 * cols as u32, 400 * rows as u32);
    render(
        &Figure {
            groups,
            envs: &envs,
            rows,
            cols,
        },
        size,
        out,
    )
}

/// A picture drawn onto a drawing area of either plotters backend.
pub trait Picture {
    /// Draws onto `root`.
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Result<()>
    where
        DB::ErrorType: 'static;
}

/// Draws `picture` into `out` at `size`: SVG when its name ends in .svg, PNG otherwise.
pub fn render(picture: &impl Picture, size: (u32, u32), out: &Path) -> Result<()> {
    register_font();
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let svg = out
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("svg"));
    let fail = |e: String| anyhow::anyhow!("writing {}: {e}", out.display());
    if svg {
        let root = SVGBackend::new(out, size).into_drawing_area();
        picture.draw(&root)?;
        root.present().map_err(|e| fail(e.to_string()))
    } else {
        let root = BitMapBackend::new(out, size).into_drawing_area();
        picture.draw(&root)?;
        root.present().map_err(|e| fail(e.to_string()))
    }
}

/// The groups' figure: one panel per env on a grid.
struct Figure<'a> {
    groups: &'a [Group],
    envs: &'a [&'a str],
    rows: usize,
    cols: usize,
}

impl Picture for Figure<'_> {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Result<()>
    where
        DB::ErrorType: 'static,
    {
        panels(root, self.groups, self.envs, self.rows, self.cols)
    }
}

fn panels<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    groups: &[Group],
    envs: &[&str],
    rows: usize,
    cols: usize,
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    root.fill(&WHITE)?;
    let areas = root.split_evenly((rows, cols));
    let mut series: Vec<&str> = groups.iter().map(|g| g.series.as_str()).collect();
    series.sort_unstable();
    series.dedup();
    for (area, env) in areas.iter().zip(envs) {
        let mine: Vec<(&Group, Band)> = groups
            .iter()
            .filter(|g| g.env == *env)
            .map(|g| (g, band(g)))
            .collect();
        let max_x = mine
            .iter()
            .flat_map(|(_, b)| b.iter().map(|p| p.0))
            .fold(1.0, f64::max)
            / 1e6;
        let max_y = mine
            .iter()
            .flat_map(|(_, b)| b.iter().map(|p| p.1 + p.2))
            .fold(10.0, f64::max)
            * 1.05;
        let mut chart = ChartBuilder::on(area)
            .caption(*env, ("sans-serif", 20))
            .margin(10)
            .x_label_area_size(40)
            .y_label_area_size(55)
            .build_cartesian_2d(0.0..max_x, 0.0..max_y)?;
        chart
            .configure_mesh()
            .x_desc("steps (millions)")
            .y_desc("mean episode length (last 100)")
            .label_style(("sans-serif", 13))
            .draw()?;
        for (g, b) in &mine {
            // A series keeps its colour across panels.
            let k = series.iter().position(|s| *s == g.series).unwrap_or(0);
            let color = Palette99::pick(k).to_rgba();
            let upper = b.iter().map(|p| (p.0 / 1e6, p.1 + p.2));
            let lower = b.iter().rev().map(|p| (p.0 / 1e6, (p.1 - p.2).max(0.0)));
            chart.draw_series(std::iter::once(Polygon::new(
                upper.chain(lower).collect::<Vec<_>>(),
                color.mix(0.2).filled(),
            )))?;
            chart
                .draw_series(LineSeries::new(
                    b.iter().map(|p| (p.0 / 1e6, p.1)),
                    color.stroke_width(2),
                ))?
                .label(format!("{} ({} seeds)", g.series, g.runs.len()))
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2))
                });
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .label_font(("sans-serif", 12))
            .draw()?;
    }
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
            plotters::style::FontStyle::Normal,
            dejavu::sans::regular(),
        );
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two seeds: (0, 100), (10, 50) and (0, 200), (10, 30). On the grid up to step 10
    /// the mean at step 10 is (50 + 30)/2 = 40 with std 10; before step 10 the mean is
    /// (100 + 200)/2 = 150, std 50.
    #[test]
    fn bands_and_tables_by_hand() {
        let env = saver_core::env::EnvSpec::new(saver_core::env::EnvKind::Angle, 2).unwrap();
        let g = Group {
            label: "a2c angle-d2".into(),
            series: "a2c".into(),
            env: "angle-d2".into(),
            runs: [
                vec![(0.0, 100.0), (10.0, 50.0)],
                vec![(0.0, 200.0), (10.0, 30.0)],
            ]
            .into_iter()
            .enumerate()
            .map(|(i, curve)| Run {
                dir: PathBuf::from(format!("s{i}")),
                config: RunConfig::paper(&env, saver_core::config::Algo::A2c, 10),
                curve,
            })
            .collect(),
        };
        let b = band(&g);
        assert_eq!(b.len(), GRID);
        assert_eq!(b.last().copied(), Some((10.0, 40.0, 10.0)));
        assert_eq!(b[0].1, 150.0);
        assert_eq!(b[0].2, 50.0);
        // Below 60: seed 0 at step 10, seed 1 at step 10 -> 10 +/- 0; final 40 +/- 10.
        let t = table(&[g], &[5], 60.0);
        assert!(
            t.contains("| a2c angle-d2 | 2 | 150.0 +/- 50.0 | 10 +/- 0 | 40.0 +/- 10.0 |"),
            "{t}"
        );
    }
}

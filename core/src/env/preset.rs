//! The built-in environments as one table: everything the code knows of a preset —
//! its dimensions, layout, bounds, maker, success rule and the paper's settings for
//! it — is one [`Preset`] row of [`PRESETS`]. A new preset is its env file, a variant
//! of [`EnvKind`] and one row here (docs/ARCHITECTURE.md shows the diff).

use super::layout::{EnvBounds, EnvLayout};
use super::{Angle, Arm, Bandit, Env, Point, Select};
use crate::{CoreError, Result};
use serde::{Deserialize, Serialize};

/// The paper's environment presets.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum EnvKind {
    /// Pairwise (step, angle) moves in a d-cube, d even (paper Fig. 3).
    Angle,
    /// Choose one dimension and a step in a d-cube (paper Fig. 4).
    Select,
    /// Two-joint robot arm reaching a goal (paper Fig. 5).
    Arm,
    /// One-step continuous bandit: two narrow optimal actions and a broad decoy (d = 1;
    /// standalone QRRL's multi-modality check, not in the paper).
    Bandit,
    /// Free moves in a d-cube, one action dim per coordinate (the paper's Fig. 1(a);
    /// actions aligned with the vector reward).
    Point,
}

impl EnvKind {
    /// Parses a preset's name ([`PRESETS`]).
    pub fn parse(s: &str) -> Result<Self> {
        <Self as clap::ValueEnum>::from_str(s, false).map_err(|_| {
            let names: Vec<_> = PRESETS.iter().map(|p| p.name).collect();
            CoreError::Config(format!(
                "env: unknown environment {:?} (expected one of {})",
                crate::clip_text(s),
                names.join(", ")
            ))
        })
    }

    /// The lower-case name.
    pub fn name(self) -> &'static str {
        self.preset().name
    }

    /// The episode length this preset always has, if it has one (the bandit: 1 step);
    /// a run of it must use it as its step limit.
    pub fn fixed_episode_steps(self) -> Option<u32> {
        self.preset().fixed_episode_steps
    }

    /// The layout of this preset at dimension `d`.
    pub fn layout(self, d: usize) -> EnvLayout {
        (self.preset().layout)(d)
    }

    /// What this preset's observations and steps can hold at dimension `d`.
    pub fn bounds(self, d: usize) -> EnvBounds {
        (self.preset().bounds)(d)
    }
}

/// One built-in environment.
pub struct Preset {
    /// Its kind (the row's index in [`PRESETS`] is the kind's).
    pub kind: EnvKind,
    /// The lower-case name (`--env NAME`, file names, the wire).
    pub name: &'static str,
    /// Why dimension d is invalid for it, if it is.
    pub bad_dim: fn(usize) -> Option<String>,
    /// Its dimension when a run names none.
    pub default_dim: usize,
    /// Its layout at dimension d.
    pub layout: fn(usize) -> EnvLayout,
    /// What its observations and steps can hold at dimension d.
    pub bounds: fn(usize) -> EnvBounds,
    /// A fresh instance at dimension d with a step limit.
    pub make: fn(usize, u32) -> Box<dyn Env>,
    /// The episode length it always has, if any (a run must use it as its limit).
    pub fixed_episode_steps: Option<u32>,
    /// Where its goal is: `None` the origin, `Some(i)` observation entries i..i+d.
    pub goal_start: Option<usize>,
    /// Which parts of an action move which coordinate of p.
    pub routing: Routing,
    /// The paper's SAVER learning rate for it (a preset the paper did not run: angle's).
    pub paper_saver_lr: f64,
    /// The paper's A2C learning rate for it.
    pub paper_a2c_lr: f64,
    /// The paper's PCPN pretraining batches for it.
    pub paper_pretrain_batches: u64,
}

/// Which parts of an action move which coordinate of p (the aligned entries): what
/// per-coordinate V-trace weighs coordinate j's step by (docs/ALGORITHM.md §16), and
/// whether QRRL's vector variant may pair action dim j with coordinate j.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Routing {
    /// Any entry may move any coordinate (arm, every custom env): one ratio a step.
    Shared,
    /// Continuous entry j moves coordinate j alone (point, bandit).
    Own,
    /// A pair's two entries (step, angle) move its two coordinates 2i, 2i+1 (angle).
    Pairs,
    /// The choice k picks the one coordinate that the continuous step moves (select).
    Choice,
}

impl Routing {
    /// Whether `layout` has the entries this routing reads: d continuous entries for
    /// `Own`, and in pairs for `Pairs`; d choices and a step for `Choice`.
    pub fn fits(self, layout: &EnvLayout) -> bool {
        let (c, k, d) = (layout.continuous, layout.choices, layout.aligned_dim);
        match self {
            Self::Shared => true,
            Self::Own => c == d,
            Self::Pairs => c == d && d.is_multiple_of(2),
            Self::Choice => k == d && c > 0,
        }
    }
}

/// Positions stay in the cube; a step moves each coordinate by at most 0.1 (angle:
/// 0.1·|sin φ|, 0.1·|cos φ|; select: 0.1 on one coordinate; point: 0.1 on each).
/// The `--dim` help, built from the table: each preset's dimensions (probed through
/// its `bad_dim` over 1..=8: one value, "even" or "any") and its default.
pub fn dim_help() -> String {
    let parts: Vec<String> = PRESETS
        .iter()
        .map(|p| {
            let ok: Vec<usize> = (1..=8).filter(|&d| (p.bad_dim)(d).is_none()).collect();
            let dims = match ok.as_slice() {
                [one] => one.to_string(),
                all if all.len() == 8 => "any".into(),
                [2, 4, 6, 8] => "even".into(),
                other => format!("{other:?} up to 8"),
            };
            format!("{}: {dims}, default {}", p.name, p.default_dim)
        })
        .collect();
    format!("State dimension d ({})", parts.join("; "))
}

fn cube_bounds(d: usize) -> EnvBounds {
    EnvBounds {
        obs_low: vec![-1.0; d],
        obs_high: vec![1.0; d],
        max_change: 0.1,
    }
}

/// The presets, in [`EnvKind`]'s order.
pub const PRESETS: [Preset; 5] = [
    Preset {
        kind: EnvKind::Angle,
        name: "angle",
        bad_dim: |d| {
            (d == 0 || !d.is_multiple_of(2))
                .then(|| format!("angle needs an even dimension >= 2, got {d}"))
        },
        default_dim: 4,
        layout: Angle::layout_at,
        bounds: cube_bounds,
        make: |d, max_steps| Box::new(Angle::new(d, max_steps)),
        fixed_episode_steps: None,
        goal_start: None,
        routing: Routing::Pairs,
        paper_saver_lr: 0.01,
        paper_a2c_lr: 0.0003,
        paper_pretrain_batches: 100_000,
    },
    Preset {
        kind: EnvKind::Select,
        name: "select",
        bad_dim: |d| (d == 0).then(|| "select needs a dimension >= 1, got 0".into()),
        default_dim: 4,
        layout: Select::layout_at,
        bounds: cube_bounds,
        make: |d, max_steps| Box::new(Select::new(d, max_steps)),
        fixed_episode_steps: None,
        goal_start: None,
        routing: Routing::Choice,
        paper_saver_lr: 0.01,
        paper_a2c_lr: 0.0001,
        paper_pretrain_batches: 10_000,
    },
    Preset {
        kind: EnvKind::Arm,
        name: "arm",
        bad_dim: |d| (d != 2).then(|| format!("the arm's hand moves in 2 dimensions, got dim {d}")),
        default_dim: 2,
        layout: |_| Arm::LAYOUT,
        // goal in [-1, 1]^2, angles in [-π, π), hand in [-2, 2]^2. Each joint turns by
        // at most 0.02π per step; the hand moves by at most its lever arm times that:
        // 2·0.02π (joint 1) + 1·0.02π (joint 2) < 0.19.
        bounds: |_| {
            let pi = std::f32::consts::PI;
            EnvBounds {
                obs_low: vec![-1.0, -1.0, -pi, -pi, -2.0, -2.0],
                obs_high: vec![1.0, 1.0, pi, pi, 2.0, 2.0],
                max_change: 0.19,
            }
        },
        make: |_, max_steps| Box::new(Arm::new(max_steps)),
        fixed_episode_steps: None,
        goal_start: Some(0),
        routing: Routing::Shared,
        paper_saver_lr: 0.003,
        paper_a2c_lr: 0.0003,
        paper_pretrain_batches: 10_000,
    },
    Preset {
        kind: EnvKind::Bandit,
        name: "bandit",
        bad_dim: |d| {
            (d != 1).then(|| format!("the bandit has one action and one coordinate, got dim {d}"))
        },
        default_dim: 1,
        layout: |_| Bandit::LAYOUT,
        // p in [0, 1]; the one step moves it by R(a) <= 1.
        bounds: |_| EnvBounds {
            obs_low: vec![0.0],
            obs_high: vec![1.0],
            max_change: 1.0,
        },
        make: |_, max_steps| Box::new(Bandit::new(max_steps)),
        fixed_episode_steps: Some(1),
        goal_start: None,
        routing: Routing::Own,
        // Not in the paper: angle's.
        paper_saver_lr: 0.01,
        paper_a2c_lr: 0.0003,
        paper_pretrain_batches: 10_000,
    },
    Preset {
        kind: EnvKind::Point,
        name: "point",
        bad_dim: |d| (d == 0).then(|| "point needs a dimension >= 1, got 0".into()),
        default_dim: 4,
        layout: Point::layout_at,
        bounds: cube_bounds,
        make: |d, max_steps| Box::new(Point::new(d, max_steps)),
        fixed_episode_steps: None,
        goal_start: None,
        routing: Routing::Own,
        // Not in the paper: angle's.
        paper_saver_lr: 0.01,
        paper_a2c_lr: 0.0003,
        paper_pretrain_batches: 100_000,
    },
];

impl EnvKind {
    /// Its row of [`PRESETS`].
    pub fn preset(self) -> &'static Preset {
        &PRESETS[self as usize]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each row sits at its kind's index, its name parses back to its kind, and its
    /// default dimension is valid, with a layout and bounds of matching sizes and a
    /// routing that fits the layout.
    #[test]
    fn the_dim_help_names_every_preset_from_the_table() {
        let help = dim_help();
        for p in PRESETS {
            assert!(
                help.contains(&format!("{}: ", p.name)),
                "{} missing: {help}",
                p.name
            );
        }
        assert!(help.contains("angle: even, default 4"), "{help}");
        assert!(help.contains("select: any, default 4"), "{help}");
        assert!(help.contains("arm: 2, default 2"), "{help}");
    }

    #[test]
    fn every_row_is_its_kinds_and_consistent() {
        for (i, p) in PRESETS.iter().enumerate() {
            assert_eq!(p.kind as usize, i, "{}", p.name);
            assert_eq!(EnvKind::parse(p.name).unwrap(), p.kind);
            let d = p.default_dim;
            assert_eq!((p.bad_dim)(d), None, "{}", p.name);
            let (l, b) = ((p.layout)(d), (p.bounds)(d));
            assert_eq!(l.aligned_dim, d, "{}", p.name);
            assert_eq!(b.obs_low.len(), l.obs_dim, "{}", p.name);
            assert_eq!((p.make)(d, 10).layout(), l, "{}", p.name);
            assert!(p.routing.fits(&l), "{}: {:?}", p.name, p.routing);
        }
    }
}

//! `--help` text that shows each setting's real default per algorithm, read from the
//! default configs themselves (so it cannot drift from them).

use super::{dotted, DEFAULT_STEPS};
use crate::algo::{recommended, HIGH_DIM_ANGLE};
use crate::config::{Algo, RunConfig};
use crate::env::{EnvKind, EnvSpec, PRESETS};
use std::collections::BTreeMap;
use std::sync::OnceLock;

/// A config's settings by dotted name ([`dotted`]).
type Settings = BTreeMap<String, String>;

/// The defaults of one setting, read from the configs they come from.
struct Defaults {
    /// (label, config) pairs: a2c and saver defaults, the paper's saver; on angle d=4.
    angle: Vec<(&'static str, Settings)>,
    /// The same on every other preset (at its default dimension), by name.
    others: Vec<(&'static str, Vec<Settings>)>,
    /// SAVER's default on angle from [`HIGH_DIM_ANGLE`] on.
    high_dim: Settings,
    /// SAVER's default on a custom env (one with continuous actions).
    custom: Settings,
    /// Every other algorithm's defaults on angle d=4, by label.
    more: Vec<(&'static str, Settings)>,
}

fn defaults() -> &'static Defaults {
    static D: OnceLock<Defaults> = OnceLock::new();
    D.get_or_init(|| {
        let preset = |kind: EnvKind, dim: usize| EnvSpec::new(kind, dim).expect("a preset");
        let tables = |kind: EnvKind, dim: usize| -> Vec<Settings> {
            let env = preset(kind, dim);
            [
                recommended(&env, Algo::A2c, DEFAULT_STEPS),
                recommended(&env, Algo::Saver, DEFAULT_STEPS),
                RunConfig::paper(&env, Algo::Saver, DEFAULT_STEPS),
            ]
            .iter()
            .map(dotted)
            .collect()
        };
        let angle = tables(EnvKind::Angle, 4);
        let others = PRESETS
            .iter()
            .filter(|p| p.kind != EnvKind::Angle)
            .map(|p| (p.name, tables(p.kind, p.default_dim)))
            .collect();
        let high_dim = dotted(&recommended(
            &preset(EnvKind::Angle, HIGH_DIM_ANGLE),
            Algo::Saver,
            DEFAULT_STEPS,
        ));
        let custom = EnvSpec::unit_custom("custom", 1.0).expect("a custom env");
        let custom = dotted(&recommended(&custom, Algo::Saver, DEFAULT_STEPS));
        let more = Algo::all()
            .iter()
            .copied()
            .filter(|a| !matches!(a, Algo::A2c | Algo::Saver))
            .map(|a| {
                let c = recommended(&preset(EnvKind::Angle, 4), a, DEFAULT_STEPS);
                (a.name(), dotted(&c))
            })
            .collect();
        Defaults {
            more,
            high_dim,
            custom,
            angle: ["a2c", "saver", "--faithful saver"]
                .into_iter()
                .zip(angle)
                .collect(),
            others,
        }
    })
}

/// A setting's value in `settings`, as the file writes it ("none" where it has none).
fn shown(settings: &Settings, path: &str) -> String {
    settings.get(path).cloned().unwrap_or_else(|| "none".into())
}

/// `text` followed by the setting's real defaults, from the default configs
/// themselves: `[default: X]` when every algorithm shares it, else one per algorithm.
pub fn help(text: &str, path: &str) -> String {
    let d = defaults();
    let values: Vec<(&str, String)> = d
        .angle
        .iter()
        .map(|(label, t)| (*label, shown(t, path)))
        .collect();
    let first = &values[0].1;
    let mut out = if values.iter().all(|(_, v)| v == first) {
        format!("{text} [default: {first}]")
    } else if values[1].1 == *first {
        format!("{text} [default: {first}; --faithful: {}]", values[2].1)
    } else {
        let parts: Vec<String> = values.iter().map(|(l, v)| format!("{l} {v}")).collect();
        format!("{text} [default: {}]", parts.join(", "))
    };
    let on_angle = |t: &Settings| shown(t, path);
    let varies: Vec<&str> = d
        .others
        .iter()
        .filter(|(_, tables)| {
            tables
                .iter()
                .zip(&d.angle)
                .any(|(o, (_, a))| on_angle(o) != on_angle(a))
        })
        .map(|(name, _)| *name)
        .collect();
    if let Some((last, rest)) = varies.split_last() {
        let names = match rest {
            [] => last.to_string(),
            _ => format!("{} and {last}", rest.join(", ")),
        };
        out.push_str(&format!(" (on angle; {names}: docs/ALGORITHM.md)"));
    }
    let high = on_angle(&d.high_dim);
    if high != values[1].1 {
        out.push_str(&format!(" (saver on angle d >= {HIGH_DIM_ANGLE}: {high})"));
    }
    let custom = shown(&d.custom, path);
    if custom != values[1].1 {
        out.push_str(&format!(" (saver on a custom env: {custom})"));
    }
    for (label, t) in &d.more {
        let v = shown(t, path);
        if v != *first {
            out.push_str(&format!(" ({label}: {v})"));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn help_shows_each_algorithms_default() {
        assert_eq!(
            help("Learning rate", "lr"),
            "Learning rate [default: a2c 0.0003, saver 0.001, --faithful saver 0.01] \
             (on angle; select and arm: docs/ALGORITHM.md) (qrrl: 0.001)"
        );
        assert_eq!(
            help("Discount γ", "gamma"),
            "Discount γ [default: 0.99] (saver on a custom env: 0.97)"
        );
        assert_eq!(
            help("Rollout", "rollout"),
            "Rollout [default: 8] (saver on a custom env: 64) (ppo: 128)"
        );
        assert_eq!(
            help("Floor", "head.log_std_min"),
            "Floor [default: a2c -inf, saver -4.6, --faithful saver -inf] \
             (saver on angle d >= 8: -1.6) (saver on a custom env: -1.6) (ppo: -4.6)"
        );
        assert_eq!(
            help("Wall", "saver.mu_raw_penalty"),
            "Wall [default: 0.0] (saver on a custom env: 0.1)"
        );
        assert_eq!(
            help("Tune", "saver.pcpn_tune_lr"),
            "Tune [default: 0.0] (saver on a custom env: 0.0001)"
        );
        assert_eq!(
            help("Bound", "head.mu_bound"),
            "Bound [default: a2c inf, saver 1.0, --faithful saver inf] (ppo: 1.0)"
        );
    }
}

//! The binary as a user runs it: bad input gets a message naming the problem, a run
//! leaves its files, PCPNs are cached and refused for another env.

use crate::{saver, temp_dir, text};
use std::process::{Command, Output};

/// `saver train --algo saver --steps 256 --out <out>` plus `extra`.
fn train_saver(out: &std::path::Path, extra: &[&str]) -> Output {
    let mut args = vec![
        "train",
        "--algo",
        "saver",
        "--steps",
        "256",
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend(extra);
    saver(&args)
}

#[test]
fn bad_flags_and_files_get_clear_errors_not_panics() {
    let dir = temp_dir("badflags");
    let unknown = dir.join("unknown.toml");
    std::fs::write(&unknown, "algo = \"a2c\"\nlearning_rate = 0.1\n").unwrap();
    let broken = dir.join("broken.toml");
    std::fs::write(&broken, "dim = [").unwrap();
    // A custom env: `saver train` cannot step it (its actors bring it).
    let custom = dir.join("custom.toml");
    std::fs::write(
        &custom,
        "[env]\nname = \"slider\"\n[env.layout]\nobs_dim = 4\ncontinuous = 2\nchoices = 0\n\
         aligned_start = 0\naligned_dim = 2\n[env.bounds]\nobs_low = [-1.0, -1.0, -1.0, -1.0]\n\
         obs_high = [1.0, 1.0, 1.0, 1.0]\nmax_change = 0.05\n",
    )
    .unwrap();
    let cases: Vec<(Vec<String>, &str)> = vec![
        (vec!["--dim".into(), "3".into()], "even"),
        (
            vec!["--env".into(), "maze".into()],
            "invalid value 'maze' for '--env <ENV>'",
        ),
        (
            vec!["--algo".into(), "dqn".into()],
            "invalid value 'dqn' for '--algo <ALGO>'",
        ),
        (vec!["--lr=-1".into()], "lr: -1"),
        (vec!["--gamma".into(), "2".into()], "gamma"),
        (vec!["--steps".into(), "0".into()], "steps"),
        (vec!["--actors".into(), "0".into()], "actors"),
        (vec!["--optimizer".into(), "sgd".into()], "optimizer"),
        (
            vec!["--env".into(), "arm".into(), "--dim".into(), "3".into()],
            "arm",
        ),
        (vec!["--steps".into(), "many".into()], "invalid value"),
        (
            vec![
                "--config".into(),
                dir.join("missing.toml").display().to_string(),
            ],
            "missing.toml",
        ),
        (
            vec!["--config".into(), unknown.display().to_string()],
            "learning_rate",
        ),
        (
            vec!["--config".into(), broken.display().to_string()],
            "broken.toml",
        ),
        (
            vec!["--config".into(), custom.display().to_string()],
            "slider-d2 is a custom env, which this build cannot step: serve the run with \
             `saver learner --config FILE`",
        ),
    ];
    for (args, want) in cases {
        let mut all = vec![
            "train".to_string(),
            "--out".into(),
            dir.join("run").display().to_string(),
        ];
        all.extend(args.clone());
        let refs: Vec<&str> = all.iter().map(String::as_str).collect();
        let o = saver(&refs);
        let t = text(&o);
        assert!(!o.status.success(), "{args:?} was accepted");
        assert!(t.contains(want), "{args:?}: expected {want:?} in {t:?}");
        assert!(!t.contains("panicked"), "{args:?} panicked: {t}");
    }
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn a_train_run_leaves_config_metrics_plot_and_checkpoint() {
    let dir = temp_dir("train");
    let run = dir.join("run");
    let o = saver(&["train", "--steps", "60000", "--out", run.to_str().unwrap()]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    // Where the training time went: the updates' seconds and share of it.
    let split = t
        .lines()
        .find(|l| l.starts_with("The learner's updates took "))
        .unwrap_or_else(|| panic!("no time split in {t}"));
    let share: f64 = split
        .split(" s (")
        .nth(1)
        .unwrap()
        .split(" %")
        .next()
        .unwrap()
        .parse()
        .unwrap();
    assert!(share > 0.0 && share <= 100.0, "{split}");
    for f in [
        "config.toml",
        "metrics.csv",
        "learning_curve.png",
        "checkpoint.safetensors",
        "policy.safetensors",
        "best.safetensors",
        "eval.csv",
    ] {
        assert!(
            t.contains(&run.join(f).display().to_string()),
            "output path of {f} not printed: {t}"
        );
    }
    // metrics.csv: a header with every column the issue names, one row per update.
    let csv = std::fs::read_to_string(run.join("metrics.csv")).unwrap();
    let header = csv.lines().next().unwrap();
    for col in [
        "steps",
        "updates",
        "wall_s",
        "steps_per_s",
        "mean_ep_len_100",
        "mean_ep_len_100_actor0",
        "policy_loss",
        "value_loss",
    ] {
        assert!(header.split(',').any(|c| c == col), "no {col} in {header}");
    }
    // 60,000 steps at 128 per update: 469 updates (the last one passes 60,000).
    assert_eq!(csv.lines().count(), 1 + 469);
    let png = std::fs::read(run.join("learning_curve.png")).unwrap();
    assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");
    // The checkpoint holds agent and optimiser slots and the counters.
    let bytes = std::fs::read(run.join("checkpoint.safetensors")).unwrap();
    let (tensors, meta) = saver_proto::decode(&bytes).unwrap();
    assert_eq!(meta["version"], "469");
    assert_eq!(meta["steps"], "60032");
    assert_eq!(meta["algo.optimizer_steps"], "469");
    for name in [
        "agent.l0.w",
        "agent.mu.w",
        "agent.log_std",
        "agent.value.w",
        "opt.ms.agent.l0.w",
    ] {
        assert!(
            tensors.iter().any(|t| t.name == name),
            "checkpoint lacks {name}"
        );
    }
    // policy.safetensors: the final weights, self-describing (the checkpoint's agent).
    let (policy, about) =
        saver_proto::decode(&std::fs::read(run.join("policy.safetensors")).unwrap()).unwrap();
    assert_eq!(
        (about["format"].as_str(), about["version"].as_str()),
        ("saver-policy/1", "469")
    );
    crate::assert_tensors_in(&policy, &tensors);
    // best.safetensors: the best evaluation (469 updates: one, at the end), which
    // `saver eval` repeats from the same starts (10 deterministic episodes, seed 0).
    let evals = std::fs::read_to_string(run.join("eval.csv")).unwrap();
    let row: Vec<&str> = evals.lines().nth(1).unwrap().split(',').collect();
    assert_eq!(evals.lines().count(), 2, "{evals}");
    assert_eq!(
        (row[0], row[1], row[2], row[5]),
        ("60032", "469", "10", "1")
    );
    let best = run.join("best.safetensors");
    let o = saver(&[
        "eval",
        best.to_str().unwrap(),
        "--episodes",
        "10",
        "--deterministic",
        "--json",
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let logged: f64 = row[3].parse().unwrap();
    let again = j["mean_return"].as_f64().unwrap();
    assert!((logged - again).abs() < 1e-4, "{logged} vs {again}");
    // The resolved config reads back as a config file.
    let config = std::fs::read_to_string(run.join("config.toml")).unwrap();
    assert!(
        config.contains("seed = 0") && config.contains("algo = \"a2c\""),
        "{config}"
    );
    // `saver eval` runs the trained policy: 20 episodes, each one ending in success or
    // at the step limit, and a picture.
    let png = dir.join("paths.png");
    let o = saver(&[
        "eval",
        run.to_str().unwrap(),
        "--episodes",
        "20",
        "--json",
        "--trajectory",
        png.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(
        (j["episodes"].as_u64(), j["env"].as_str()),
        (Some(20), Some("angle-d4"))
    );
    let rate = j["success_rate"].as_f64().unwrap();
    let (p10, max) = (
        j["length_percentiles"]["p10"].as_u64().unwrap(),
        j["length_percentiles"]["max"].as_u64().unwrap(),
    );
    assert!(
        (0.0..=1.0).contains(&rate) && 1 <= p10 && p10 <= max && max <= 1000,
        "{j}"
    );
    assert_eq!(j["final_distance"].as_array().unwrap().len(), 4);
    assert_eq!(&std::fs::read(&png).unwrap()[..8], b"\x89PNG\r\n\x1a\n");
    // ... and repeats the run bit for bit in another folder.
    let again = dir.join("again");
    let cfg = run.join("config.toml");
    let o = saver(&[
        "train",
        "--config",
        cfg.to_str().unwrap(),
        "--out",
        again.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let (repeated, _) =
        saver_proto::decode(&std::fs::read(again.join("checkpoint.safetensors")).unwrap()).unwrap();
    assert_eq!(repeated.len(), tensors.len());
    crate::assert_tensors_in(&tensors, &repeated);
    assert_eq!(
        std::fs::read_to_string(again.join("config.toml")).unwrap(),
        config
    );
    // `saver plot` groups runs of the same settings (seeds apart) into one band, as SVG
    // too, with its table beside it, into a folder it makes.
    let svg = dir.join("figures/new/curves.svg");
    let o = saver(&[
        "plot",
        run.to_str().unwrap(),
        again.to_str().unwrap(),
        "--out",
        svg.to_str().unwrap(),
        "--at",
        "60000",
    ]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(std::fs::read_to_string(&svg).unwrap().starts_with("<svg"));
    let md = std::fs::read_to_string(dir.join("figures/new/curves.md")).unwrap();
    assert!(md.contains("| a2c angle-d4 | 2 |"), "{md}");
    std::fs::remove_dir_all(dir).ok();
}

/// `saver eval` on a run folder acts with the policy the run published, normaliser
/// included: a PPO run with `--ppo-obs-norm` scores the same from its folder as from
/// its policy.safetensors (the folder read its checkpoint's agent without the mean and
/// scale before: 0.69 against 0.95 on a 30 k-step run). Without policy.safetensors the
/// folder is refused by name rather than evaluated wrong.
#[test]
fn eval_of_a_run_folder_reads_through_its_normaliser() {
    let dir = temp_dir("eval-norm");
    let run = dir.join("run");
    let r = run.to_str().unwrap();
    let train = "train --algo ppo --env angle --dim 4 --ppo-obs-norm true --steps 8192 --out";
    let args: Vec<&str> = train.split(' ').chain([r]).collect();
    let o = saver(&args);
    assert!(o.status.success(), "{}", text(&o));
    let score = |source: &str| {
        let o = saver(&[
            "eval",
            source,
            "--episodes",
            "5",
            "--deterministic",
            "--json",
        ]);
        assert!(o.status.success(), "{}", text(&o));
        let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        j["mean_return"].as_f64().unwrap()
    };
    let policy = run.join("policy.safetensors");
    assert_eq!(score(r), score(policy.to_str().unwrap()));
    std::fs::remove_file(&policy).unwrap();
    let o = saver(&["eval", r]);
    let t = text(&o);
    assert!(
        !o.status.success()
            && t.contains("normalised observations")
            && t.contains("policy.safetensors"),
        "{t}"
    );
    std::fs::remove_dir_all(dir).ok();
}

/// `saver repro` on a tiny arm grid with a variant of the user's: every run, the figure,
/// a table row per series, a manifest naming each SAVER run's PCPN, and a rerun that
/// finds every run finished.
#[test]
fn repro_runs_a_grid_with_a_users_variant_and_says_what_made_it() {
    let dir = temp_dir("repro");
    let (out, pcpn) = (dir.join("out"), dir.join("pcpn"));
    let args = [
        "repro",
        "fig5",
        "--steps",
        "16384",
        "--seeds",
        "0,1",
        "--no-faithful",
        "--pretrain-batches",
        "200",
        "--jobs",
        "2",
        "--out",
        out.to_str().unwrap(),
        "--pcpn-dir",
        pcpn.to_str().unwrap(),
        "--variant",
        "fast=--algo saver --lr 0.003",
    ];
    let o = saver(&args);
    assert!(o.status.success(), "{}", text(&o));
    let root = out.join("fig5");
    let table = std::fs::read_to_string(root.join("table.md")).unwrap();
    for row in [
        "| a2c arm-d2 | 2 |",
        "| saver arm-d2 | 2 |",
        "| saver (lr 0.003) arm-d2 | 2 |",
    ] {
        assert!(table.contains(row), "{row} missing from\n{table}");
    }
    assert!(std::fs::read_to_string(root.join("figure.svg"))
        .unwrap()
        .starts_with("<svg"));
    let manifest = std::fs::read_to_string(root.join("manifest.md")).unwrap();
    assert!(
        manifest.contains("--variant 'fast=--algo saver --lr 0.003'"),
        "{manifest}"
    );
    // Both SAVER series share the one PCPN of 200 batches; A2C runs name none.
    let stored: Vec<_> = std::fs::read_dir(&pcpn).unwrap().collect();
    assert_eq!(stored.len(), 1, "{stored:?}");
    let pcpn_lines = manifest
        .lines()
        .filter(|l| l.contains("PCPN weights sha256"))
        .count();
    assert_eq!(pcpn_lines, 4, "{manifest}");
    assert!(manifest.contains("pretrained 200 batches"), "{manifest}");
    let a2c = manifest
        .lines()
        .find(|l| l.contains("arm-d2-a2c-seed1"))
        .unwrap();
    assert!(!a2c.contains("PCPN"), "{a2c}");
    // A variant named like a built-in one would share its folders: refused.
    let mut clash = args.to_vec();
    clash.extend(["--variant", "a2c=--algo a2c --lr 0.001"]);
    let o = saver(&clash);
    assert!(!o.status.success());
    assert!(
        text(&o).contains("share the run folder arm-d2-a2c-seed0"),
        "{}",
        text(&o)
    );
    // Again: nothing left to run.
    let o = saver(&args);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("6 runs in"), "{}", text(&o));
    assert!(text(&o).contains("(6 finished already)"), "{}", text(&o));
    std::fs::remove_dir_all(dir).ok();
}

/// `saver train | head -0`: the reader is gone before the run prints; the run still
/// finishes and writes its checkpoint, and nothing panics.
#[test]
fn a_closed_stdout_ends_the_output_not_the_run() {
    let dir = temp_dir("closed-pipe");
    let run = dir.join("run");
    let mut child = Command::new(env!("CARGO_BIN_EXE_saver"))
        .args(["train", "--steps", "2048", "--out", run.to_str().unwrap()])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take());
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    assert!(run.join("checkpoint.safetensors").exists());
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn pcpn_is_pretrained_once_reused_and_refused_for_another_env() {
    let dir = temp_dir("pcpn");
    let store = dir.join("store");
    let s = store.to_str().unwrap();
    let o = saver(&[
        "pretrain",
        "--env",
        "angle",
        "--dim",
        "2",
        "--batches",
        "20",
        "--pcpn-dir",
        s,
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let file = crate::only_pcpn(&store);
    let (_, meta) = saver_proto::decode(&std::fs::read(&file).unwrap()).unwrap();
    for key in [
        "env_spec",
        "architecture",
        "pretrain",
        "held_out_loss",
        "weights_sha256",
    ] {
        assert!(
            meta.contains_key(key),
            "PCPN metadata lacks {key}: {meta:?}"
        );
    }
    let settings: saver_core::config::PretrainConfig =
        serde_json::from_str(&meta["pretrain"]).unwrap();
    assert_eq!(settings.batches, 20);
    assert!(meta["held_out_loss"].parse::<f32>().unwrap().is_finite());

    // train --algo saver finds it in the store instead of pretraining again.
    let run = dir.join("run");
    let same = ["--dim", "2", "--pcpn-dir", s, "--pretrain-batches", "20"];
    let o = train_saver(&run, &same);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(t.contains("Using the cached PCPN"), "{t}");

    // A PCPN for d = 2 is refused for a d = 4 run, with the reason.
    let o = train_saver(
        &dir.join("run4"),
        &["--dim", "4", "--pcpn", file.to_str().unwrap()],
    );
    let t = text(&o);
    assert!(!o.status.success());
    assert!(
        t.contains("pretrained for angle-d2") && t.contains("angle-d4"),
        "{t}"
    );

    // A corrupted file is refused by its hash.
    let mut bytes = std::fs::read(&file).unwrap();
    let n = bytes.len();
    bytes[n - 3] ^= 0x40;
    std::fs::write(&file, &bytes).unwrap();
    let o = train_saver(&run, &same);
    assert!(!o.status.success());
    assert!(text(&o).contains("corrupt"), "{}", text(&o));
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn pretraining_that_diverges_stops_with_an_error_and_saves_nothing() {
    // SPEC.md: at too high a rate the PCPN loss explodes (0.046 → 2e7 as published).
    // At lr 5 it passes 100x its initial held-out loss within ~150 batches.
    let dir = temp_dir("diverge");
    let store = dir.join("store");
    let o = saver(&[
        "pretrain",
        "--env",
        "angle",
        "--dim",
        "2",
        "--batches",
        "400",
        "--pretrain-lr",
        "5",
        "--pcpn-dir",
        store.to_str().unwrap(),
    ]);
    let t = text(&o);
    assert!(!o.status.success(), "{t}");
    assert!(t.contains("diverged") && t.contains("--pretrain-lr"), "{t}");
    assert!(!store.join("pcpn-angle-d2.safetensors").exists());
    std::fs::remove_dir_all(dir).ok();
}

/// `saver bench` end to end at a tiny size (no timing is asserted, only that every
/// part runs and reports against the peak).
#[test]
fn bench_runs_every_part_and_reports_shares_of_peak() {
    let o = saver(&[
        "bench",
        "--dims",
        "2",
        "--seconds",
        "0.05",
        "--cycle-updates",
        "3",
        "--no-services",
    ]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    for want in [
        "GFLOP/s",
        "of peak",
        "a2c    d=4: 3 updates",
        "saver  d=4: 3 updates",
    ] {
        assert!(t.contains(want), "{want:?} missing from:\n{t}");
    }
}

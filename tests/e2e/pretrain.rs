//! PCPN pretraining is one function of (env spec, pretraining settings), whoever asks:
//! `saver train`, `saver pretrain` and the pcpn-trainer's Pretrain call make the same
//! weights bit for bit, and a stored PCPN of other settings is never used in their place.

use crate::{only_pcpn, saver_ok, temp_dir};
use saver_core::config::{OptimizerKind, PretrainConfig, SampleDistribution};
use saver_core::env::{EnvKind, EnvSpec};
use saver_pcpn_trainer::service::{fetch, serve, PcpnService};
use saver_pcpn_trainer::{load_pcpn, PcpnStore, StoreError};
use std::path::Path;

/// Small settings, none of them a default, so a default anywhere would show.
fn settings() -> PretrainConfig {
    PretrainConfig {
        optimizer: OptimizerKind::Adam,
        lr: 0.002,
        batches: 40,
        batch_size: 32,
        quantiles: 8,
        seed: 7,
        samples: SampleDistribution::Reset,
        walk_samples: 0,
    }
}

const FLAGS: [&str; 14] = [
    "--pretrain-optimizer",
    "adam",
    "--pretrain-lr",
    "0.002",
    "--pretrain-batches",
    "40",
    "--pretrain-batch-size",
    "32",
    "--pretrain-quantiles",
    "8",
    "--pretrain-seed",
    "7",
    "--pretrain-samples",
    "reset",
];

#[test]
fn three_entry_points_make_the_same_pcpn_and_other_settings_are_never_reused() {
    let dir = temp_dir("pretrain-entry");
    let spec = EnvSpec::new(EnvKind::Angle, 2).unwrap();
    let s = |p: &Path| p.to_str().unwrap().to_string();
    let (by_train, by_pretrain, by_rpc) =
        (dir.join("train"), dir.join("pretrain"), dir.join("rpc"));

    let run = dir.join("run");
    let mut train = vec!["train", "--algo", "saver", "--env", "angle", "--dim", "2"];
    let (run_s, train_s) = (s(&run), s(&by_train));
    train.extend([
        "--steps",
        "256",
        "--actors",
        "2",
        "--out",
        &run_s,
        "--pcpn-dir",
        &train_s,
    ]);
    train.extend(FLAGS);
    saver_ok(&train);
    let pretrain_s = s(&by_pretrain);
    let mut pretrain = vec![
        "pretrain",
        "--env",
        "angle",
        "--dim",
        "2",
        "--pcpn-dir",
        &pretrain_s,
    ];
    pretrain.extend(FLAGS);
    saver_ok(&pretrain);

    let rt = tokio::runtime::Runtime::new().unwrap();
    let listener = rt
        .block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))
        .unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    rt.spawn(serve(
        PcpnService::new(&by_rpc),
        listener,
        std::future::pending(),
    ));
    let bytes = rt
        .block_on(fetch(&url, &spec, &settings(), &Default::default()))
        .unwrap();

    let dev = candle_core::Device::Cpu;
    let files = [
        only_pcpn(&by_train),
        only_pcpn(&by_pretrain),
        only_pcpn(&by_rpc),
    ];
    let infos: Vec<_> = files
        .iter()
        .map(|f| load_pcpn(f, &spec, &dev).unwrap().1)
        .collect();
    for (f, info) in files.iter().zip(&infos) {
        assert_eq!(info.pretrain, settings(), "{}", f.display());
        assert_eq!(
            info.weights_sha256,
            infos[0].weights_sha256,
            "{}",
            f.display()
        );
        assert_eq!(f.file_name(), files[0].file_name());
    }
    assert_eq!(bytes, std::fs::read(&files[2]).unwrap());
    // The run names its PCPN and pretraining settings in config.toml.
    let config = std::fs::read_to_string(run.join("config.toml")).unwrap();
    assert!(
        config.contains(&format!("pcpn_sha256 = \"{}\"", infos[0].weights_sha256)),
        "{config}"
    );
    assert!(
        config.contains("[pretrain]\noptimizer = \"adam\"\nlr = 0.002\nbatches = 40"),
        "{config}"
    );

    // A PCPN of other settings under this file name is refused by name, not used.
    let other = PretrainConfig {
        seed: 8,
        ..settings()
    };
    let store = PcpnStore::new(&by_pretrain);
    std::fs::rename(&files[1], store.path_for(&spec, &other)).unwrap();
    match store.find(&spec, &other, &dev) {
        Err(e @ StoreError::SettingsMismatch { .. }) => {
            assert!(e.to_string().contains("seed: 7"), "{e}")
        }
        Err(e) => panic!("wrong error: {e}"),
        Ok(_) => panic!("a PCPN of seed 7 was used for seed 8"),
    }
    // A train run that asks for other settings gets a PCPN of its own next to it.
    let other_run = s(&dir.join("run2"));
    let again: Vec<&str> = train
        .iter()
        .map(|&a| match a {
            "40" => "41",
            a if a == run_s => &other_run,
            a => a,
        })
        .collect();
    let out = saver_ok(&again);
    assert!(out.contains("pretraining one (41 batches)"), "{out}");
    assert_eq!(std::fs::read_dir(&by_train).unwrap().count(), 2);
    std::fs::remove_dir_all(dir).ok();
}

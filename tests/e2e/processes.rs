//! The `saver` binary as separate OS processes: pcpn-trainer, learner and 4 actors on
//! 127.0.0.1 (ports chosen by the OS), weights fetched with `saver weights`.

use crate::{assert_tensors_in, saver, temp_dir};
use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};

/// A child process killed when dropped (also when a test fails).
pub struct Proc(pub Child);

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Starts `saver args…` and returns it with the address it reports ("… on ADDR").
pub fn serve(args: &[&str]) -> (Proc, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_saver"))
        .args(args)
        .stderr(Stdio::piped())
        .stdout(Stdio::null())
        .spawn()
        .unwrap();
    let stderr = child.stderr.take().unwrap();
    let mut lines = BufReader::new(stderr).lines();
    let addr = loop {
        let line = lines
            .next()
            .expect("the server exited before listening")
            .unwrap();
        if let Some(rest) = line.split(" on ").nth(1) {
            break rest.split([';', ' ']).next().unwrap().to_string();
        }
    };
    // Keep draining stderr so the child never blocks on a full pipe.
    std::thread::spawn(move || for _ in lines {});
    (Proc(child), format!("http://{addr}"))
}

/// A port the OS had free a moment ago, on 127.0.0.1.
fn free_port() -> String {
    let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    l.local_addr().unwrap().to_string()
}

/// The raw HTTP answer to a GET of /metrics at `addr` with the extra header lines
/// `headers`.
fn get_metrics(addr: &str, headers: &str) -> String {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    write!(s, "GET /metrics HTTP/1.1\r\nHost: saver\r\n{headers}\r\n").unwrap();
    let mut text = String::new();
    s.read_to_string(&mut text).unwrap();
    text
}

/// Scrapes Prometheus metrics at `addr` and parses the text format into
/// `name{labels}` -> value (comment lines checked to be HELP or TYPE).
fn scrape(addr: &str) -> std::collections::HashMap<String, f64> {
    let text = get_metrics(addr, "");
    let (head, body) = text.split_once("\r\n\r\n").unwrap();
    assert!(head.starts_with("HTTP/1.1 200"), "{head}");
    body.lines()
        .filter(|l| !l.is_empty())
        .filter(|l| {
            let comment = l.starts_with('#');
            assert!(
                !comment || l.starts_with("# HELP") || l.starts_with("# TYPE"),
                "{l}"
            );
            !comment
        })
        .map(|l| {
            let (name, value) = l.rsplit_once(' ').unwrap();
            (name.to_string(), value.parse::<f64>().unwrap())
        })
        .collect()
}

#[test]
fn learner_and_four_actor_processes_equal_the_embedded_run() {
    let dir = temp_dir("procs");
    let d = |p: &str| dir.join(p).display().to_string();
    let run = [
        "--algo",
        "saver",
        "--dim",
        "2",
        "--actors",
        "4",
        "--steps",
        "640",
        "--pretrain-batches",
        "20",
    ];
    let (store_metrics, learner_metrics) = (free_port(), free_port());
    let (_store, store_url) = serve(&[
        "pcpn-trainer",
        "--listen",
        "127.0.0.1:0",
        "--store",
        &d("store"),
        "--metrics",
        &store_metrics,
    ]);
    let ok = saver(&["healthcheck", "--addr", &store_url]);
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );

    let mut largs = vec!["learner", "--listen", "127.0.0.1:0", "--pcpn", &store_url];
    largs.extend(["--metrics", learner_metrics.as_str()]);
    let out_dir = d("grpc-run");
    largs.extend(run);
    largs.extend(["--out", out_dir.as_str()]);
    let (_learner, url) = serve(&largs);
    let actors: Vec<Proc> = (0..4)
        .map(|_| {
            Proc(
                Command::new(env!("CARGO_BIN_EXE_saver"))
                    .args(["actor", "--learner", &url])
                    .stdout(Stdio::null())
                    .stderr(Stdio::null())
                    .spawn()
                    .unwrap(),
            )
        })
        .collect();
    // 640 steps = 20 updates of 4 x 8; wait (bounded) for version 20.
    let weights = d("weights.safetensors");
    let w = saver(&[
        "weights",
        "--learner",
        &url,
        "--min-version",
        "20",
        "--out",
        &weights,
    ]);
    let text = String::from_utf8_lossy(&w.stdout).to_string();
    assert!(
        w.status.success(),
        "{text}{}",
        String::from_utf8_lossy(&w.stderr)
    );
    assert!(
        text.starts_with("version 20") && text.contains("agent.mu.w"),
        "{text}"
    );
    // `status --watch` asks until the run is finished, then exits; each answer is
    // one JSON object.
    let watched = saver(&["status", "--watch", "0.1", "--json", "--learner", &url]);
    assert!(watched.status.success());
    let last: serde_json::Value = serde_json::from_str(
        String::from_utf8_lossy(&watched.stdout)
            .lines()
            .last()
            .unwrap(),
    )
    .unwrap();
    // Prometheus: the learner's counters after 20 updates of 4 actors, and the
    // store's pretraining progress.
    let m = scrape(&learner_metrics);
    assert_eq!(m["saver_version"], 20.0, "{m:?}");
    assert_eq!(m["saver_steps"], 640.0);
    assert!(m["saver_rollouts_accepted_total"] >= 80.0, "{m:?}");
    assert_eq!(m["saver_update_seconds_count"], 20.0, "{m:?}");
    let queued = m["saver_rollout_queue"];
    assert!((0.0..=8.0).contains(&queued), "{m:?}");
    assert!(
        m.contains_key("saver_update_value{name=\"actor_loss\"}"),
        "{m:?}"
    );
    let p = scrape(&store_metrics);
    assert_eq!(
        p["saver_pretrain_batches_done{env=\"angle-d2\"}"], 20.0,
        "{p:?}"
    );
    assert_eq!(
        (last["finished"].as_bool(), last["version"].as_u64()),
        (Some(true), Some(20))
    );
    drop(actors);

    // The embedded run with the same PCPN file, seed and actor count.
    let pcpn = crate::only_pcpn(&dir.join("store")).display().to_string();
    let mut targs = vec!["train", "--pcpn", pcpn.as_str()];
    let emb_dir = d("embedded");
    targs.extend(run);
    targs.extend(["--out", emb_dir.as_str()]);
    let t = saver(&targs);
    assert!(t.status.success(), "{}", String::from_utf8_lossy(&t.stderr));

    let (remote, meta) = saver_proto::decode(&std::fs::read(&weights).unwrap()).unwrap();
    assert_eq!(meta["version"], "20");
    // The weights say what they are: env, algorithm, policy and the PCPN behind them.
    let pcpn_info = saver_pcpn_trainer::load_pcpn(
        std::path::Path::new(&pcpn),
        &saver_core::env::EnvSpec::new(saver_core::env::EnvKind::Angle, 2).unwrap(),
        &candle_core::Device::Cpu,
    )
    .unwrap()
    .1;
    assert_eq!(meta["format"], "saver-policy/1");
    assert_eq!(
        (meta["algo"].as_str(), meta["env"].as_str()),
        ("saver", "angle-d2")
    );
    assert_eq!(meta["pcpn_sha256"], pcpn_info.weights_sha256);
    assert_eq!(meta["policy_family"], "gaussian-mlp");
    let params: std::collections::BTreeMap<String, f64> =
        serde_json::from_str(&meta["policy_params"]).unwrap();
    assert_eq!(params["mu_bound"], 1.0);
    assert!(meta["architecture"].contains("agent.mu.w"), "{meta:?}");
    // The file alone is enough to evaluate the policy.
    let o = saver(&[
        "eval",
        &weights,
        "--episodes",
        "3",
        "--deterministic",
        "--json",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(
        (j["env"].as_str(), j["version"].as_u64()),
        (Some("angle-d2"), Some(20))
    );
    let (local, _) =
        saver_proto::decode(&std::fs::read(dir.join("embedded/checkpoint.safetensors")).unwrap())
            .unwrap();
    assert_tensors_in(&remote, &local);
    std::fs::remove_dir_all(dir).ok();
}

/// `saver status --json` of the learner at `url` as (key, value) pairs.
fn status(url: &str) -> Option<std::collections::HashMap<String, String>> {
    let out = saver(&["status", "--json", "--learner", url]);
    out.status.success().then(|| {
        let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        v.as_object()
            .unwrap()
            .iter()
            .map(|(k, v)| (k.clone(), v.to_string()))
            .collect()
    })
}

/// Polls `status` until `cond` holds; panics after `limit`.
fn wait_until(url: &str, limit: std::time::Duration, what: &str, cond: impl Fn(u64, u64) -> bool) {
    let end = std::time::Instant::now() + limit;
    loop {
        if let Some(s) = status(url) {
            let (v, a) = (s["version"].parse().unwrap(), s["actors"].parse().unwrap());
            if cond(v, a) {
                return;
            }
        }
        assert!(
            std::time::Instant::now() < end,
            "not within {limit:?}: {what}; status {:?}",
            status(url)
        );
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
}

fn version(url: &str) -> u64 {
    status(url).expect("the learner answers")["version"]
        .parse()
        .unwrap()
}

fn actor(url: &str) -> Proc {
    Proc(
        Command::new(env!("CARGO_BIN_EXE_saver"))
            .args(["actor", "--learner", url])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap(),
    )
}

#[test]
fn killed_actors_and_a_killed_learner_come_back() {
    let dir = temp_dir("kill");
    let out = dir.join("run").display().to_string();
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let listen = format!("127.0.0.1:{port}");
    let learner_args = [
        "learner",
        "--listen",
        &listen,
        "--algo",
        "a2c",
        "--dim",
        "2",
        "--actors",
        "2",
        "--steps",
        "100000000",
        "--checkpoint-every",
        "10",
        "--round-timeout",
        "1",
        "--out",
        &out,
    ];
    let (learner, url) = serve(&learner_args);
    let mut actors = vec![actor(&url), actor(&url)];
    wait_until(
        &url,
        std::time::Duration::from_secs(60),
        "20 updates",
        |v, a| v >= 20 && a == 2,
    );

    // kill -9 one actor: training goes on with the other; a restarted one is back fast.
    drop(actors.remove(0));
    let v = version(&url);
    wait_until(
        &url,
        std::time::Duration::from_secs(30),
        "training on with 1 actor",
        |w, a| w >= v + 10 && a == 1,
    );
    actors.push(actor(&url));
    wait_until(
        &url,
        std::time::Duration::from_secs(5),
        "the restarted actor back",
        |_, a| a == 2,
    );
    let v = version(&url);
    wait_until(
        &url,
        std::time::Duration::from_secs(30),
        "training with 2 again",
        |w, _| w >= v + 10,
    );

    // kill -9 the learner (and the actors, so that nothing trains on after the restart
    // until the weights are compared): the restart serves the checkpoint's weights.
    drop(actors);
    drop(learner);
    let checkpoint = std::path::Path::new(&out).join("checkpoint.safetensors");
    let (saved, meta) = saver_proto::decode(&std::fs::read(&checkpoint).unwrap()).unwrap();
    let saved_version: u64 = meta["version"].parse().unwrap();
    assert!(
        saved_version >= 20 && saved_version % 10 == 0,
        "checkpoint at {saved_version}"
    );
    let (_learner, url) = serve(&learner_args);
    let fetched = dir.join("resumed.safetensors").display().to_string();
    let w = saver(&["weights", "--learner", &url, "--out", &fetched]);
    assert!(w.status.success(), "{}", String::from_utf8_lossy(&w.stderr));
    let (resumed, meta) = saver_proto::decode(&std::fs::read(&fetched).unwrap()).unwrap();
    // The checkpoint's weights, under a version above every one the killed learner
    // published (its metrics.csv names the newest): no client sees a number twice.
    let rows = std::fs::read_to_string(std::path::Path::new(&out).join("metrics.csv")).unwrap();
    let versions: Vec<u64> = rows
        .lines()
        .skip(1)
        .map(|l| l.split(',').nth(1).unwrap().parse().unwrap())
        .collect();
    assert!(versions.windows(2).all(|w| w[0] < w[1]), "{versions:?}");
    assert_eq!(
        versions.last(),
        Some(&saved_version),
        "rows after the checkpoint dropped"
    );
    let served: u64 = meta["version"].parse().unwrap();
    assert!(served >= saved_version, "{served} < {saved_version}");
    assert_tensors_in(&resumed, &saved);
    // Actors join the resumed run and versions keep increasing from the checkpoint's.
    let _actors = [actor(&url), actor(&url)];
    wait_until(
        &url,
        std::time::Duration::from_secs(60),
        "training after the restart",
        |w, _| w >= served + 10,
    );
    std::fs::remove_dir_all(dir).ok();
}

/// Resident memory of a process in KiB (Linux /proc).
fn rss_kib(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let line = status.lines().find(|l| l.starts_with("VmRSS:")).unwrap();
    line.split_whitespace().nth(1).unwrap().parse().unwrap()
}

/// 64 actor processes against one learner: after a warm-up of 50 updates and 300 more
/// (the allocator's arenas, the checkpoint buffers and 64 streams reach their size), the
/// learner's resident memory grows by at most 2 MiB over the next 600 updates
/// (38,400 rollouts). Measured: 29,848 → 30,188 → 30,340 KiB at versions 54, 356 and
/// 958 (+152 KiB in the checked window). With a leak planted in `Hub::submit` (each
/// rollout's observations forgotten) the same window grew 3,852 KiB and fails;
/// the bound before (+50 % + 32 MiB, ~47 MiB) passed it.
#[test]
fn sixty_four_actor_soak_keeps_the_learners_memory_flat() {
    let dir = temp_dir("soak");
    let out = dir.join("run").display().to_string();
    let (learner, url) = serve(&[
        "learner",
        "--listen",
        "127.0.0.1:0",
        "--algo",
        "a2c",
        "--dim",
        "2",
        "--actors",
        "64",
        "--steps",
        "100000000",
        "--checkpoint-every",
        "50",
        "--out",
        &out,
    ]);
    let _actors: Vec<Proc> = (0..64).map(|_| actor(&url)).collect();
    wait_until(
        &url,
        std::time::Duration::from_secs(120),
        "64 actors training",
        |v, a| v >= 50 && a == 64,
    );
    let mut at = vec![(version(&url), rss_kib(learner.0.id()))];
    for more in [300, 600] {
        let v0 = at.last().unwrap().0;
        wait_until(
            &url,
            std::time::Duration::from_secs(600),
            "more updates",
            |v, _| v >= v0 + more,
        );
        at.push((version(&url), rss_kib(learner.0.id())));
    }
    eprintln!("64-actor soak: learner (version, RSS KiB) {at:?}");
    let ((v1, rss1), (v2, rss2)) = (at[1], at[2]);
    assert!(
        rss2 <= rss1 + 2 * 1024,
        "the learner grew from {rss1} KiB to {rss2} KiB over {} updates",
        v2 - v1
    );
    std::fs::remove_dir_all(dir).ok();
}

/// `saver train --out DIR` for 4 actors on angle d = 2 (A2C, 1,500 updates).
fn train_cmd(out: &str) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_saver"));
    c.args([
        "train", "--algo", "a2c", "--dim", "2", "--actors", "4", "--steps", "48000",
    ])
    .args(["--out", out]);
    c
}

#[test]
fn a_run_stopped_with_sigterm_and_resumed_ends_bit_identical() {
    let dir = temp_dir("sigterm");
    let (whole, parts) = (dir.join("whole"), dir.join("parts"));
    let (whole_s, parts_s) = (whole.display().to_string(), parts.display().to_string());
    let ok = train_cmd(&whole_s).output().unwrap();
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );

    // The same run, stopped with SIGTERM once 300 updates are in metrics.csv.
    let child = train_cmd(&parts_s)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let metrics = parts.join("metrics.csv");
    while std::fs::read_to_string(&metrics).map_or(0, |s| s.lines().count()) < 301 {
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    // SAFETY: kill(2) on our own child's pid.
    unsafe { libc::kill(child.id() as i32, libc::SIGTERM) };
    let first = child.wait_with_output().unwrap();
    assert!(first.status.success());
    let said = String::from_utf8_lossy(&first.stdout);
    assert!(said.contains("stopped early"), "{said}");
    let (_, meta) =
        saver_proto::decode(&std::fs::read(parts.join("checkpoint.safetensors")).unwrap()).unwrap();
    let stopped_at: u64 = meta["version"].parse().unwrap();
    assert!(
        (300..1500).contains(&stopped_at),
        "stopped at version {stopped_at}"
    );

    // Started again: resumes and ends where the uninterrupted run ended, bit for bit.
    let again = train_cmd(&parts_s).output().unwrap();
    assert!(
        again.status.success(),
        "{}",
        String::from_utf8_lossy(&again.stderr)
    );
    let load = |p: &std::path::Path| {
        saver_proto::decode(&std::fs::read(p.join("checkpoint.safetensors")).unwrap()).unwrap()
    };
    let ((a, ma), (b, mb)) = (load(&whole), load(&parts));
    assert_eq!(
        (&ma["version"], &mb["version"]),
        (&"1500".to_string(), &"1500".to_string())
    );
    assert_eq!(a.len(), b.len());
    assert_tensors_in(&a, &b);
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn a_learner_with_no_actors_stops_on_sigterm_and_removes_its_weights_dir() {
    let dir = temp_dir("sigterm-idle");
    let wdir = dir.join("weights");
    let (wdir_s, out_s) = (
        wdir.display().to_string(),
        dir.join("run").display().to_string(),
    );
    let (mut learner, _url) = serve(&[
        "learner",
        "--listen",
        "127.0.0.1:0",
        "--steps",
        "1000",
        "--out",
        &out_s,
        "--weights-dir",
        &wdir_s,
    ]);
    // Version 0 is written before any actor comes.
    let v0 = wdir.join("v0.safetensors");
    assert!((0..500).any(|_| {
        std::thread::sleep(std::time::Duration::from_millis(10));
        v0.exists()
    }));
    // SAFETY: kill(2) on our own child's pid.
    unsafe { libc::kill(learner.0.id() as i32, libc::SIGTERM) };
    // Waiting for its 16 actors must not keep it from stopping (it used to).
    let status = (0..1000).find_map(|_| {
        std::thread::sleep(std::time::Duration::from_millis(10));
        learner.0.try_wait().unwrap()
    });
    assert!(status.is_some_and(|s| s.success()), "{status:?}");
    assert!(!wdir.exists(), "the weights directory is removed");
    std::fs::remove_dir_all(dir).ok();
}

/// The metrics endpoint follows the gRPC port's rule: on a non-loopback address with
/// neither token nor TLS the server refuses to start, saying why; with a token a
/// scrape without it gets 401 and one with it the metrics.
#[test]
fn the_metrics_endpoint_needs_the_token_off_loopback() {
    let dir = temp_dir("metrics-access");
    let store = dir.join("store").display().to_string();
    let port = free_port().rsplit_once(':').unwrap().1.to_string();
    let open = format!("0.0.0.0:{port}");
    let base = ["pcpn-trainer", "--listen", "127.0.0.1:0", "--store", &store];
    let out = Command::new(env!("CARGO_BIN_EXE_saver"))
        .args(base)
        .args(["--metrics", &open])
        .env_remove("SAVER_TOKEN")
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(
        err.contains("refusing to serve metrics on 0.0.0.0"),
        "{err}"
    );

    let mut args = base.to_vec();
    args.extend(["--metrics", &open, "--token", "metrics-s3cret"]);
    let (_store, _) = serve(&args);
    let local = format!("127.0.0.1:{port}");
    let refused = get_metrics(&local, "");
    assert!(refused.starts_with("HTTP/1.1 401"), "{refused}");
    let wrong = get_metrics(&local, "Authorization: Bearer metrics-s3cre\r\n");
    assert!(wrong.starts_with("HTTP/1.1 401"), "{wrong}");
    let ok = get_metrics(&local, "Authorization: Bearer metrics-s3cret\r\n");
    assert!(ok.starts_with("HTTP/1.1 200"), "{ok}");
    assert!(!ok.contains("needs the server's token"), "{ok}");
}

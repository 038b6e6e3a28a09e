//! The `dray` binary end to end: generate, preprocess, verify, info, and
//! the errors a user sees.

use std::path::Path;
use std::process::{Command, Output};

fn dray(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_dray"))
        .args(args)
        .env("RUST_LOG", "warn")
        .output()
        .expect("run dray")
}

fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[test]
fn generate_preprocess_verify_info() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("plant.ply");
    let db = dir.path().join("plant.db");
    let out = dray(&[
        "generate",
        "plant",
        "--triangles",
        "20000",
        "--out",
        s(&model),
    ]);
    assert!(out.status.success(), "{}", text(&out));

    let out = dray(&[
        "preprocess",
        s(&model),
        "--out",
        s(&db),
        "--max-triangles",
        "256",
        "--threads",
        "2",
    ]);
    assert!(out.status.success(), "{}", text(&out));

    let out = dray(&["verify", s(&db)]);
    assert!(out.status.success(), "{}", text(&out));
    assert!(text(&out).contains("ok"), "{}", text(&out));

    let out = dray(&["info", s(&db), "--json"]);
    assert!(out.status.success(), "{}", text(&out));
    let stdout = String::from_utf8(out.stdout).unwrap();
    let info: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    assert_eq!(info["input_triangles"], 20000);
    assert!(info["voxels"].as_u64().unwrap() > 10);
    assert!(info["replication_factor"].as_f64().unwrap() >= 1.0);

    let out = dray(&["info", s(&db)]);
    assert!(text(&out).contains("replication factor"), "{}", text(&out));

    // Render with negative coordinates written plainly, and every output.
    let (png, pfm, ids) = (
        dir.path().join("a.png"),
        dir.path().join("d.pfm"),
        dir.path().join("p.u32"),
    );
    let out = dray(&[
        "render",
        s(&db),
        "--eye",
        "-20,15,-25",
        "--look",
        "40,2,30",
        "--width",
        "64",
        "--height",
        "48",
        "--shadows",
        "--reflections",
        "1",
        "--out",
        s(&png),
        "--depth-out",
        s(&pfm),
        "--primid-out",
        s(&ids),
        "--repeat",
        "3",
        "--json",
    ]);
    assert!(out.status.success(), "{}", text(&out));
    let last = String::from_utf8(out.stdout)
        .unwrap()
        .lines()
        .last()
        .unwrap()
        .to_string();
    let json: serde_json::Value = serde_json::from_str(&last).unwrap();
    assert_eq!(json["width"], 64);
    assert!(json["hit_fraction"].as_f64().unwrap() > 0.05, "{last}");
    assert!(json["shadow_rays"].as_u64().unwrap() > 0, "{last}");
    // Shadow rays, like all rays, are reported by the best of the passes.
    let best = json["shadow_mrays_per_s"].as_f64().unwrap();
    let median = json["shadow_mrays_per_s_median"].as_f64().unwrap();
    assert!(median > 0.0 && best >= median, "{last}");
    assert_eq!(json["seconds"].as_array().unwrap().len(), 3, "{last}");
    assert!(std::fs::read(&png).unwrap().starts_with(b"\x89PNG"));
    assert_eq!(std::fs::metadata(&ids).unwrap().len(), 64 * 48 * 4);
    assert_eq!(
        std::fs::metadata(&pfm).unwrap().len(),
        "Pf\n64 48\n-1.0\n".len() as u64 + 64 * 48 * 4
    );

    // One sample per pixel is the default's image; more are averaged, and
    // the figures count them all; the depth and ids stay sample 0's.
    let view = |spp: &str, png: &Path, pfm: &Path| {
        let out = dray(&[
            "render",
            s(&db),
            "--eye",
            "-20,15,-25",
            "--look",
            "40,2,30",
            "--width",
            "64",
            "--height",
            "48",
            "--shadows",
            "--reflections",
            "1",
            "--out",
            s(png),
            "--depth-out",
            s(pfm),
            "--spp",
            spp,
            "--json",
        ]);
        assert!(out.status.success(), "{}", text(&out));
        let stdout = String::from_utf8(out.stdout).unwrap();
        serde_json::from_str::<serde_json::Value>(stdout.lines().last().unwrap()).unwrap()
    };
    let (png1, pfm1) = (dir.path().join("spp1.png"), dir.path().join("spp1.pfm"));
    let one = view("1", &png1, &pfm1);
    assert_eq!(one["samples"], 1);
    assert_eq!(std::fs::read(&png1).unwrap(), std::fs::read(&png).unwrap());
    let (png3, pfm3) = (dir.path().join("spp3.png"), dir.path().join("spp3.pfm"));
    let three = view("3", &png3, &pfm3);
    assert_eq!(three["samples"], 3);
    assert_eq!(three["primary_rays"], 3 * 64 * 48);
    assert_ne!(std::fs::read(&png3).unwrap(), std::fs::read(&png).unwrap());
    assert_eq!(std::fs::read(&pfm3).unwrap(), std::fs::read(&pfm).unwrap());

    // A camera the cluster would refuse is refused here in the same words,
    // naming the flag.
    let out = dray(&[
        "render",
        s(&db),
        "--eye",
        "0,0,0",
        "--look",
        "0,10,0",
        "--up",
        "0,-2,0",
    ]);
    assert!(!out.status.success(), "{}", text(&out));
    let words = dray_protocol::check_camera(&dray_protocol::Camera {
        eye: [0.0; 3],
        look: [0.0, 10.0, 0.0],
        up: [0.0, -2.0, 0.0],
        fov_y_deg: 50.0,
    })
    .unwrap_err();
    assert_eq!(words.field, dray_protocol::CameraField::Up);
    assert!(
        text(&out).contains(&format!("error: --up: {}", words.message)),
        "{}",
        text(&out)
    );

    // Corrupt the middle of the voxels file: verify names a voxel and fails.
    let voxels = db.join("voxels.dray");
    let mut bytes = std::fs::read(&voxels).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid] ^= 0xFF;
    std::fs::write(&voxels, bytes).unwrap();
    let out = dray(&["verify", s(&db)]);
    assert!(!out.status.success());
    assert!(text(&out).contains("voxel "), "{}", text(&out));
}

/// `--memory-mb` bounds the whole process, whatever the model size: a model
/// that needs several out-of-core chunks at 64 MiB stays under it.
#[test]
fn preprocessing_stays_within_the_memory_budget() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("plant.ply");
    let out = dray(&[
        "generate",
        "plant",
        "--triangles",
        "600000",
        "--out",
        s(&model),
    ]);
    assert!(out.status.success(), "{}", text(&out));
    let db = dir.path().join("db");
    let out = dray(&[
        "preprocess",
        s(&model),
        "--out",
        s(&db),
        "--memory-mb",
        "64",
    ]);
    assert!(out.status.success(), "{}", text(&out));
    let stdout = String::from_utf8(out.stdout).unwrap();
    if let Some(rest) = stdout.split("peak RSS ").nth(1) {
        let mib: u64 = rest.split_whitespace().next().unwrap().parse().unwrap();
        assert!(mib < 64, "peak RSS {mib} MiB over a 64 MiB budget");
    } else {
        // Only Linux reports it (from /proc).
        #[cfg(target_os = "linux")]
        panic!("no peak RSS reported: {stdout}");
    }
    assert!(dray(&["verify", s(&db)]).status.success());
}

#[test]
fn bad_input_is_a_clear_error_not_a_panic() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("broken.ply");
    std::fs::write(&bad, b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n\0\0\0").unwrap();
    let out = dray(&["preprocess", s(&bad), "--out", s(&dir.path().join("db"))]);
    assert!(!out.status.success());
    let t = text(&out);
    assert!(t.contains("broken.ply") && t.contains("byte"), "{t}");
    assert!(!t.contains("panicked"), "{t}");
    assert!(!dir.path().join("db").exists());

    let out = dray(&["verify", s(&dir.path().join("nothing-here"))]);
    assert!(!out.status.success());
    assert!(text(&out).contains("no such database"), "{}", text(&out));

    let out = dray(&["preprocess", s(&bad), "--out", "x", "--copies", "2x0x1"]);
    assert!(!out.status.success());
    assert!(text(&out).contains("AxBxC"), "{}", text(&out));
}

#[test]
fn a_corrupt_database_is_named_once_with_its_problem() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("plant.ply");
    let db = dir.path().join("plant.db");
    let gen = dray(&[
        "generate",
        "plant",
        "--triangles",
        "10000",
        "--out",
        s(&model),
    ]);
    assert!(gen.status.success(), "{}", text(&gen));
    let pre = dray(&["preprocess", s(&model), "--out", s(&db)]);
    assert!(pre.status.success(), "{}", text(&pre));
    let manifest = db.join("manifest.dray");
    let mut bytes = std::fs::read(&manifest).unwrap();
    let last = bytes.len() - 1;
    bytes[last] ^= 0xff;
    std::fs::write(&manifest, &bytes).unwrap();
    let out = dray(&["render", s(&db)]);
    assert!(!out.status.success());
    let t = text(&out);
    let line = t
        .lines()
        .find(|l| l.starts_with("error:"))
        .unwrap_or_else(|| panic!("{t}"));
    assert!(
        line.contains("manifest.dray") && line.contains("corrupt"),
        "{t}"
    );
    // The cause once, not once from the message and again from the chain.
    assert_eq!(line.matches("corrupt").count(), 1, "{t}");
    assert!(!t.contains("panicked"), "{t}");
}

#[test]
fn certs_init_issues_a_certificate_per_node_of_the_config() {
    let dir = tempfile::tempdir().unwrap();
    let certs = dir.path().join("certs");
    let config = concat!(env!("CARGO_MANIFEST_DIR"), "/config/examples/local.toml");
    let out = dray(&["certs", "init", s(&certs), "--config", config]);
    assert!(out.status.success(), "{}", text(&out));
    for f in [
        "ca.pem",
        "ca/ca.key",
        "scheduler.pem",
        "scheduler.key",
        "display.pem",
        "client-0.pem",
    ] {
        assert!(certs.join(f).is_file(), "{f} missing: {}", text(&out));
    }
    // The CA key is not among the node keys.
    assert!(!certs.join("ca.key").exists());
    // The CA is never replaced.
    let again = dray(&["certs", "init", s(&certs), "--nodes", "client-9"]);
    assert!(!again.status.success());
    assert!(text(&again).contains("already exists"), "{}", text(&again));
    let none = dray(&["certs", "init", s(&dir.path().join("x"))]);
    assert!(!none.status.success());
    assert!(text(&none).contains("--nodes"), "{}", text(&none));

    // A node added later, and one node's bundle: no CA key, no other key.
    let before = std::fs::read(certs.join("client-0.pem")).unwrap();
    let add = dray(&["certs", "add", s(&certs), "--node", "client-9"]);
    assert!(add.status.success(), "{}", text(&add));
    assert!(certs.join("client-9.key").is_file());
    assert_eq!(std::fs::read(certs.join("client-0.pem")).unwrap(), before);
    let twice = dray(&["certs", "add", s(&certs), "--node", "client-9"]);
    assert!(!twice.status.success());
    assert!(
        text(&twice).contains("client-9.pem already exists"),
        "{}",
        text(&twice)
    );
    let out_dir = dir.path().join("host-9");
    let b = dray(&[
        "certs",
        "bundle",
        s(&certs),
        "--node",
        "client-9",
        "--out",
        s(&out_dir),
    ]);
    assert!(b.status.success(), "{}", text(&b));
    let mut files: Vec<String> = std::fs::read_dir(&out_dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    files.sort();
    assert_eq!(files, ["ca.pem", "client-9.key", "client-9.pem"]);
    let unknown = dray(&["certs", "bundle", s(&certs), "--node", "client-5"]);
    assert!(!unknown.status.success());
    assert!(
        text(&unknown).contains("client-5.pem"),
        "{}",
        text(&unknown)
    );
    let no_ca = dray(&["certs", "add", s(&out_dir), "--node", "client-8"]);
    assert!(!no_ca.status.success());
    assert!(
        text(&no_ca).contains("the CA key is missing"),
        "{}",
        text(&no_ca)
    );
}

/// Logs written to a file or a pipe are plain text: no ANSI colour codes,
/// whatever the level, and `RUST_LOG` still chooses what is logged.
#[test]
fn logs_to_a_pipe_have_no_colour_codes() {
    let dir = tempfile::tempdir().unwrap();
    let certs = dir.path().join("certs");
    let out = Command::new(env!("CARGO_BIN_EXE_dray"))
        .args(["certs", "init", s(&certs), "--nodes", "client-0"])
        .env("RUST_LOG", "debug")
        .env_remove("NO_COLOR")
        .output()
        .expect("run dray");
    assert!(out.status.success(), "{}", text(&out));
    let log = String::from_utf8_lossy(&out.stderr);
    assert!(
        log.contains("INFO"),
        "RUST_LOG=debug logged no info line:\n{log}"
    );
    assert!(
        !log.contains('\x1b'),
        "colour codes in a piped log:\n{log:?}"
    );
    let quiet = dray(&["certs", "init", s(&dir.path().join("q")), "--nodes", "a"]);
    assert!(quiet.status.success(), "{}", text(&quiet));
    assert!(!String::from_utf8_lossy(&quiet.stderr).contains("INFO"));
}

#[test]
fn experiment_runs_a_file_and_names_a_bad_key() {
    let dir = tempfile::tempdir().unwrap();
    let tiny = Path::new(env!("CARGO_MANIFEST_DIR")).join("experiments/tiny.toml");
    let out_dir = dir.path().join("out");
    // From the temporary directory, so that the model cache
    // (data/experiments/models) is made there.
    let run = |args: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_dray"))
            .args(args)
            .current_dir(dir.path())
            .env("RUST_LOG", "warn")
            .output()
            .expect("run dray")
    };
    let out = run(&["experiment", s(&tiny), "--quick", "--out", s(&out_dir)]);
    assert!(out.status.success(), "{}", text(&out));
    assert!(text(&out).contains("4 of 4 runs done"), "{}", text(&out));
    for file in [
        "points.csv",
        "frames.csv",
        "summary.md",
        "plot1-fps-by-latency_ms.png",
    ] {
        assert!(out_dir.join(file).is_file(), "no {file}");
    }
    assert!(dir
        .path()
        .join("data/experiments/models/plant-20000-seed3.vdb")
        .is_dir());

    let bad = dir.path().join("bad.toml");
    std::fs::write(
        &bad,
        std::fs::read_to_string(&tiny)
            .unwrap()
            .replace("\"clients.threads\"", "\"clients.thread\"")
            .replace(
                "../config/",
                &format!("{}/config/", env!("CARGO_MANIFEST_DIR")),
            ),
    )
    .unwrap();
    let out = run(&["experiment", s(&bad)]);
    assert!(!out.status.success());
    let msg = text(&out);
    assert!(
        msg.contains("bad.toml: [set] clients.thread: unknown field `thread`"),
        "{msg}"
    );
    assert!(!msg.contains("panicked"), "{msg}");
}

/// `dray render` refuses an image size the config refuses, in the config's
/// words (before touching the database, so a missing one does not matter),
/// and `dray walkthrough` refuses 0 frames instead of writing one.
#[test]
fn image_sizes_and_frame_counts_out_of_range_are_refused_with_the_config_words() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("none.db");
    let out = dray(&["render", s(&db), "--width", "100000", "--height", "100000"]);
    assert!(!out.status.success(), "{}", text(&out));
    let words = dray_config::check_image_side("render.width", 100000)
        .unwrap_err()
        .to_string();
    let problem = words.strip_prefix("render.width: ").unwrap();
    assert!(
        text(&out).contains(&format!("error: --width: {problem}")),
        "{}",
        text(&out)
    );
    let out = dray(&["render", s(&db), "--height", "0"]);
    assert!(
        text(&out).contains("error: --height: 0 is not in 1..=16384"),
        "{}",
        text(&out)
    );

    let walk = dir.path().join("walk.toml");
    let out = dray(&["walkthrough", s(&db), "--frames", "0", "--out", s(&walk)]);
    assert!(!out.status.success(), "{}", text(&out));
    assert!(
        text(&out).contains("error: --frames: 0 is not in 1..=100000"),
        "{}",
        text(&out)
    );
    assert!(!walk.exists());
}

/// `dray render`'s shading flags are checked by the functions that check
/// the config and received messages, and refused in their words before the
/// database is opened.
#[test]
fn shading_flags_out_of_range_are_refused_with_the_shared_words() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("none.db");
    for (flag, value, words) in [
        (
            "--reflectance",
            "1.5",
            dray_protocol::check_reflectance(1.5).unwrap_err(),
        ),
        (
            "--reflections",
            "17",
            dray_protocol::check_reflection_depth(17).unwrap_err(),
        ),
        (
            "--light",
            "0,0,0",
            dray_protocol::check_light_dir([0.0; 3]).unwrap_err(),
        ),
        ("--spp", "0", dray_protocol::check_samples(0).unwrap_err()),
        (
            "--spp",
            "1025",
            dray_protocol::check_samples(1025).unwrap_err(),
        ),
    ] {
        let out = dray(&["render", s(&db), flag, value]);
        assert!(!out.status.success(), "{}", text(&out));
        assert!(
            text(&out).contains(&format!("error: {flag}: {words}")),
            "{flag} {value}: {}",
            text(&out)
        );
    }
}

/// The frames' directory of `cluster`, `node` and `sim` is `--save-frames`;
/// `--frames` is only ever a count (`demo`, `walkthrough`).
#[test]
fn frames_is_a_count_and_save_frames_a_directory() {
    for args in [
        &["cluster", "c.toml", "--frames", "out"][..],
        &["sim", "c.toml", "--frames", "out"],
        &[
            "node", "--config", "c.toml", "--role", "display", "--frames", "out",
        ],
    ] {
        let out = dray(args);
        assert!(!out.status.success(), "{args:?}");
        assert!(
            text(&out).contains("unexpected argument '--frames'"),
            "{args:?}: {}",
            text(&out)
        );
    }
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("missing.toml");
    let out = dray(&["sim", s(&missing), "--save-frames", s(dir.path())]);
    assert!(!out.status.success());
    // The flag is accepted: what fails is reading the config.
    assert!(text(&out).contains("missing.toml"), "{}", text(&out));
    let out = dray(&["demo", "--frames", "dir"]);
    assert!(
        text(&out).contains("invalid value 'dir' for '--frames"),
        "{}",
        text(&out)
    );
}

/// `dray node` without `--role` takes its node from a launcher's rank; with
/// none, or one that does not fit the config, it says what is missing and
/// starts nothing.
#[test]
fn a_node_without_role_names_the_launcher_variables_it_looked_for() {
    let config = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/examples/local.toml");
    let node = |vars: &[(&str, &str)]| {
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_dray"));
        cmd.args(["node", "--config", s(&config)])
            .env("RUST_LOG", "warn");
        for var in [
            "SLURM_PROCID",
            "SLURM_NTASKS",
            "OMPI_COMM_WORLD_RANK",
            "PMIX_RANK",
            "PMI_RANK",
            "JOB_COMPLETION_INDEX",
            "KUBERNETES_SERVICE_HOST",
        ] {
            cmd.env_remove(var);
        }
        cmd.envs(vars.iter().copied());
        cmd.output().unwrap()
    };
    let out = node(&[]);
    assert!(!out.status.success());
    assert!(
        text(&out).contains("no --role given and no launcher's rank in the environment")
            && text(&out).contains("SLURM_PROCID"),
        "{}",
        text(&out)
    );
    let out = node(&[("SLURM_PROCID", "2"), ("SLURM_NTASKS", "3")]);
    assert!(
        text(&out).contains("Slurm started 3 processes (SLURM_NTASKS), but the config has 8 ranks"),
        "{}",
        text(&out)
    );
    let out = node(&[("PMI_RANK", "one")]);
    assert!(
        text(&out).contains("PMI_RANK=\"one\" is not a whole number"),
        "{}",
        text(&out)
    );
    let out = dray(&["node", "--config", s(&config), "--index", "1"]);
    assert!(text(&out).contains("--role"), "{}", text(&out));
}

#[test]
fn shard_cuts_a_database_and_a_store_of_another_shard_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("plant.ply");
    let db = dir.path().join("db");
    assert!(dray(&[
        "generate",
        "plant",
        "--triangles",
        "10000",
        "--out",
        s(&model)
    ])
    .status
    .success());
    assert!(dray(&[
        "preprocess",
        s(&model),
        "--out",
        s(&db),
        "--max-triangles",
        "256"
    ])
    .status
    .success());
    let shards = dir.path().join("shards");
    let out = dray(&["shard", s(&db), "--of", "2", "--out", s(&shards)]);
    assert!(out.status.success(), "{}", text(&out));
    assert!(text(&out).contains("shard 1/2:"), "{}", text(&out));
    let out = dray(&["verify", s(&shards.join("shard-1"))]);
    assert!(out.status.success(), "{}", text(&out));
    // Again: nothing is written over.
    let out = dray(&["shard", s(&db), "--of", "2", "--out", s(&shards)]);
    assert!(
        !out.status.success() && text(&out).contains("exists"),
        "{}",
        text(&out)
    );
    // A store serving 0/2 from shard 1 of 2 stops before it starts.
    let local = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/examples/local.toml");
    let text_cfg = std::fs::read_to_string(local)
        .unwrap()
        .replace("../../data/plant.vdb", s(&db))
        .replace(
            "address = \"127.0.0.1:7410\"",
            &format!(
                "address = \"127.0.0.1:7410\"\ndatabase = \"{}\"",
                s(&shards.join("shard-1"))
            ),
        );
    let cfg = dir.path().join("c.toml");
    std::fs::write(&cfg, text_cfg).unwrap();
    let out = dray(&[
        "node",
        "--config",
        s(&cfg),
        "--role",
        "store",
        "--index",
        "0",
    ]);
    assert!(!out.status.success());
    assert!(
        text(&out).contains("stores[0].database:") && text(&out).contains("is shard 1/2"),
        "{}",
        text(&out)
    );
}

/// A node whose address is not on its host (a launcher that placed its
/// rank elsewhere) stops at once, naming the key to change.
#[test]
fn a_node_whose_address_is_not_on_its_host_names_the_key() {
    let dir = tempfile::tempdir().unwrap();
    let local = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/examples/local.toml");
    // 192.0.2.0/24 is for documentation: no host has it.
    let config_text = std::fs::read_to_string(local)
        .unwrap()
        .replace("\"127.0.0.1:7400\"", "\"192.0.2.7:7400\"");
    let cfg = dir.path().join("c.toml");
    std::fs::write(&cfg, config_text).unwrap();
    let certs = dir.path().join("certs");
    let out = dray(&["certs", "init", s(&certs), "--config", s(&cfg)]);
    assert!(out.status.success(), "{}", text(&out));
    let out = dray(&["node", "--config", s(&cfg), "--role", "scheduler"]);
    assert!(!out.status.success());
    assert!(
        text(&out).contains("192.0.2.7:7400")
            && text(&out).contains("is not this host's (change scheduler.address"),
        "{}",
        text(&out)
    );
}

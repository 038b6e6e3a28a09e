//! The example parses; each kind of mistake is named by its key.

use dray_config::{Compression, Config, ConfigError, MissMode, TilePolicy};
use std::path::Path;

fn example_text() -> String {
    std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/local.toml"))
        .unwrap()
}

#[test]
fn the_local_example_loads() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/local.toml");
    let cfg = Config::load(&path).unwrap();
    assert_eq!(cfg.clients.count, 4);
    assert_eq!(cfg.clients.miss_mode, MissMode::Suspend);
    assert_eq!(cfg.clients.pixel_compression, Compression::Lz4);
    let zstd = example_text().replacen(
        "pixel_compression = \"lz4\"",
        "pixel_compression = \"zstd\"",
        1,
    );
    assert_eq!(
        Config::parse(&zstd).unwrap().clients.pixel_compression,
        Compression::Zstd
    );
    let unset = example_text().replacen("pixel_compression = \"lz4\"", "", 1);
    assert_eq!(
        Config::parse(&unset).unwrap().clients.pixel_compression,
        Compression::Lz4
    );
    assert_eq!(cfg.store_addrs().unwrap().len(), 2);
    assert!(cfg.scheduler_addr().unwrap().ip().is_loopback());
    assert!(cfg.certs.dir.starts_with(path.parent().unwrap()));
    assert_eq!(
        cfg.node_names(),
        [
            "scheduler",
            "display",
            "store-0",
            "store-1",
            "client-0",
            "client-1",
            "client-2",
            "client-3"
        ]
    );
    assert_eq!(cfg.cache_bytes(), 256_000_000);
    assert_eq!(
        (cfg.clients.tiles_ahead, cfg.clients.max_tiles_ahead),
        (16, Some(32))
    );
    assert!(!cfg.links.client_store.is_shaped());
    assert_eq!(cfg.scheduler.max_block_px, 128);
    assert_eq!(cfg.render.samples, 1);
    let more = example_text().replacen("samples = 1 ", "samples = 1024 ", 1);
    assert_eq!(Config::parse(&more).unwrap().render.samples, 1024);
    let unset = example_text().replacen("samples = 1 ", "", 1);
    assert_eq!(
        Config::parse(&unset).unwrap().render.samples,
        1,
        "the default"
    );
    let unset = example_text().replacen("max_block_px = 128", "", 1);
    let cfg = Config::parse(&unset).unwrap();
    assert_eq!(cfg.scheduler.max_block_px, 128, "the default");
}

/// Replaces the first occurrence of `from` in the example and returns the
/// validation error.
fn broken(from: &str, to: &str) -> ConfigError {
    let text = example_text();
    assert!(text.contains(from), "example lacks {from:?}");
    Config::parse(&text.replacen(from, to, 1)).unwrap_err()
}

fn assert_names(err: ConfigError, key: &str, problem: &str) {
    let msg = err.to_string();
    assert!(msg.contains(key), "{msg:?} should name {key:?}");
    assert!(msg.contains(problem), "{msg:?} should say {problem:?}");
}

#[test]
fn mistakes_name_their_key() {
    assert_names(
        broken("cache_mb = 256", "cache_mb = 0"),
        "clients.cache_mb",
        "at least one voxel",
    );
    assert_names(
        broken("# shard = \"1/2\"", "shard = \"0/2\""),
        "stores",
        "1 modulo 2",
    );
    assert_names(
        broken("# shard = \"1/2\"", "shard = \"2/2\""),
        "stores[1].shard",
        "I/N",
    );
    assert_names(
        broken("light_dir = [0.3, 1.0, 0.2]", "light_dir = [0.0, 0.0, 0.0]"),
        "render.light_dir",
        "non-zero",
    );
    assert_names(
        broken("reflective = \"all\"", "reflective = \"some\""),
        "reflective",
        "not a reflection rule",
    );
    assert_names(
        broken("address = \"127.0.0.1:7411\"", "address = \"localhost\""),
        "stores[1].address",
        "HOST:PORT",
    );
    assert_names(
        broken(
            "address = \"127.0.0.1:7411\"",
            "address = \"127.0.0.1:7400\"",
        ),
        "stores[1].address",
        "also scheduler.address",
    );
    assert_names(
        broken("samples = 1 ", "samples = 0 "),
        "render.samples",
        "0 is not in 1..=1024",
    );
    assert_names(
        broken("samples = 1 ", "samples = 1025 "),
        "render.samples",
        "1025 is not in 1..=1024",
    );
    assert_names(
        broken("tile_size = 32", "tile_size = 1000"),
        "render.tile_size",
        "1..=256",
    );
    assert_names(
        broken("count = 4", "count = 0"),
        "clients.count",
        "at least one",
    );
    assert_names(
        broken("fov_y_deg = 50.0", "fov_y_deg = 190.0"),
        "render.camera.fov_y_deg",
        "(0, 180)",
    );
    assert_names(
        broken("up = [0.0, 1.0, 0.0]", "up = [0.0, 0.0, 0.0]"),
        "render.camera.up",
        "zero vector",
    );
    assert_names(
        broken("up = [0.0, 1.0, 0.0]", "up = [0.0, -3.0, 30.0]"),
        "render.camera.up",
        "parallel",
    );
    assert_names(
        broken(
            "[links.client_store]\nlatency_ms = 0.0",
            "[links.client_store]\nlatency_ms = -3.0",
        ),
        "links.client_store.latency_ms",
        "between 0",
    );
    assert_names(
        broken("loss = 0.0", "loss = 1.5"),
        "links.client_store.loss",
        "[0, 1)",
    );
    assert_names(
        broken("count = 4", "count = 5000"),
        "clients.count",
        "more than 1024",
    );
    assert_names(
        broken("max_tiles_ahead = 32", "max_tiles_ahead = 65"),
        "clients.max_tiles_ahead",
        "over 64",
    );
    assert_names(
        broken("max_block_px = 128", "max_block_px = 512"),
        "scheduler.max_block_px",
        "more than 256",
    );
}

/// Shard counts whose common multiple overflows any integer are refused,
/// not a panic.
#[test]
fn shard_counts_of_large_primes_are_refused() {
    let primes = [997, 991, 983, 977, 971, 967, 953, 947];
    let mut text = example_text();
    for (i, p) in primes.iter().enumerate() {
        text.push_str(&format!(
            "\n[[stores]]\naddress = \"127.0.0.1:{}\"\nshard = \"0/{p}\"\n",
            7500 + i
        ));
    }
    assert_names(
        Config::parse(&text).unwrap_err(),
        "stores",
        "too many or too mixed",
    );
}

#[test]
fn unknown_fields_and_wrong_types_are_refused_by_toml() {
    assert_names(
        broken("threads = 2", "thread = 2"),
        "",
        "unknown field `thread`",
    );
    assert_names(
        broken("miss_mode = \"suspend\"", "miss_mode = \"hope\""),
        "",
        "unknown variant `hope`",
    );
    assert_names(
        broken(
            "pixel_compression = \"lz4\"",
            "pixel_compression = \"gzip\"",
        ),
        "",
        "unknown variant `gzip`",
    );
    let e = broken("width = 1280", "width = \"wide\"");
    assert!(matches!(e, ConfigError::Parse { .. }));
    assert!(e.to_string().contains("width"), "{e}");
}

#[test]
fn the_tile_policy_is_chosen_by_name_from_a_closed_set() {
    let cfg = Config::parse(&example_text()).unwrap();
    assert_eq!(cfg.scheduler.policy, TilePolicy::Affinity);
    let random = example_text().replacen("policy = \"affinity\"", "policy = \"random\"", 1);
    assert_eq!(
        Config::parse(&random).unwrap().scheduler.policy,
        TilePolicy::Random
    );
    let unset = example_text().replacen("policy = \"affinity\"", "", 1);
    assert_eq!(
        Config::parse(&unset).unwrap().scheduler.policy,
        TilePolicy::Affinity,
        "the default"
    );
    for p in TilePolicy::ALL {
        assert_eq!(p.name().parse::<TilePolicy>(), Ok(p));
    }
    let e = broken("policy = \"affinity\"", "policy = \"fastest\"");
    assert!(matches!(e, ConfigError::Parse { .. }));
    assert_names(e, "scheduler.policy", "the choices are affinity, random");
    // The boolean it replaced is refused, not silently ignored.
    assert_names(
        broken("policy = \"affinity\"", "affinity = true"),
        "",
        "unknown field `affinity`",
    );
}

#[test]
fn a_missing_file_names_its_path() {
    let e = Config::load(Path::new("/nonexistent/dray.toml")).unwrap_err();
    assert!(e.to_string().contains("/nonexistent/dray.toml"), "{e}");
}

#[test]
fn tiles_ahead_grow_to_32_unless_fixed() {
    let text = example_text();
    let unset = text.replacen("max_tiles_ahead = 32", "", 1);
    let cfg = Config::parse(&unset).unwrap();
    assert_eq!(cfg.clients.most_tiles_ahead(), 32);
    let many = unset.replacen("tiles_ahead = 16", "tiles_ahead = 48", 1);
    assert_eq!(Config::parse(&many).unwrap().clients.most_tiles_ahead(), 48);
    let fixed = text.replacen("max_tiles_ahead = 32", "max_tiles_ahead = 16", 1);
    assert_eq!(
        Config::parse(&fixed).unwrap().clients.most_tiles_ahead(),
        16
    );
}

/// The example with `table` appended.
fn with_table(table: &str) -> Result<Config, ConfigError> {
    Config::parse(&format!("{}\n{table}\n", example_text()))
}

#[test]
fn node_links_are_unshaped_by_default_and_validated_by_key() {
    let cfg = Config::parse(&example_text()).unwrap();
    assert!(!cfg.links.store_uplink.is_shaped());
    assert!(!cfg.links.client_downlink.is_shaped());
    assert_eq!(cfg.links.store_disk.bandwidth_bps(), None);

    let cfg = with_table(
        "[links.store_uplink]\nbandwidth_mbps = 1000.0\n\
         [links.client_downlink]\nlatency_ms = 2.0\nbandwidth_mbps = 100.0\n\
         [links.store_disk]\nbandwidth_mbps = 440.0\nlatency_ms = 8.0",
    )
    .unwrap();
    assert_eq!(cfg.links.store_uplink.bandwidth_bps(), Some(1_000_000_000));
    assert_eq!(cfg.links.client_downlink.bandwidth_bps(), Some(100_000_000));
    assert_eq!(cfg.links.store_disk.bandwidth_bps(), Some(440_000_000));
    assert_eq!(
        cfg.links.store_disk.access_time(),
        std::time::Duration::from_millis(8)
    );

    assert_names(
        with_table("[links.store_uplink]\nbandwidth_mbps = 0.0").unwrap_err(),
        "links.store_uplink.bandwidth_mbps",
        "from 0.1 to 1000000 Mbit/s",
    );
    // Positive but too slow to carry anything: refused here, naming the
    // key, not at start naming a node.
    assert_names(
        with_table("[links.client_downlink]\nbandwidth_mbps = 1e-9").unwrap_err(),
        "links.client_downlink.bandwidth_mbps",
        "from 0.1 to 1000000 Mbit/s",
    );
    assert_names(
        broken("# bandwidth_mbps = 100.0", "bandwidth_mbps = 0.05"),
        "links.client_store.bandwidth_mbps",
        "from 0.1",
    );
    assert_eq!(
        with_table("[links.client_downlink]\nbandwidth_mbps = 0.1")
            .unwrap()
            .links
            .client_downlink
            .bandwidth_bps(),
        Some(100_000)
    );
    assert_names(
        with_table("[links.client_downlink]\nloss = 1.0").unwrap_err(),
        "links.client_downlink.loss",
        "[0, 1)",
    );
    assert_names(
        with_table("[links.store_disk]\nbandwidth_mbps = -55.0").unwrap_err(),
        "links.store_disk.bandwidth_mbps",
        "from 0.1",
    );
    assert_names(
        with_table("[links.store_disk]\nlatency_ms = 1e9").unwrap_err(),
        "links.store_disk.latency_ms",
        "between 0 and 60000",
    );
    // A disk neither jitters nor loses reads: those keys do not exist there.
    assert_names(
        with_table("[links.store_disk]\nloss = 0.1").unwrap_err(),
        "",
        "unknown field `loss`",
    );
}

#[test]
fn image_sizes_are_checked_by_one_function_naming_the_key() {
    assert_names(
        broken("width = 1280", "width = 100000"),
        "render.width",
        "100000 is not in 1..=16384",
    );
    assert_names(
        broken("height = 720", "height = 0"),
        "render.height",
        "0 is not in 1..=16384",
    );
    // The same words for the command line's flags (`dray render`).
    let e = dray_config::check_image_side("--width", 100000).unwrap_err();
    assert_eq!(e.to_string(), "--width: 100000 is not in 1..=16384");
    assert!(dray_config::check_image_side("--height", 16384).is_ok());
}

#[test]
fn frames_in_flight_are_bounded_in_memory() {
    let big = |ahead: u32, ids: bool| {
        example_text()
            .replacen("width = 1280", "width = 16384", 1)
            .replacen("height = 720", "height = 16384", 1)
            .replacen("tile_size = 32", "tile_size = 64", 1)
            .replacen(
                "output = \"../../out\"",
                &format!("output = \"../../out\"\nframes_ahead = {ahead}"),
                1,
            )
            .replacen(
                "reflectance = 0.6",
                &format!("reflectance = 0.6\ndepth_and_ids = {ids}"),
                1,
            )
    };
    // 16 frames of 16384 x 16384 would hold 16 GiB of colors.
    assert_names(
        Config::parse(&big(16, false)).unwrap_err(),
        "display.frames_ahead",
        "16 frames of 16384x16384 in flight hold 16.0 GiB",
    );
    assert!(Config::parse(&big(4, false)).is_ok());
    // Depth and ids triple the bytes a pixel.
    let e = Config::parse(&big(2, true)).unwrap_err();
    assert_names(e, "display.frames_ahead", "render.depth_and_ids");
    assert!(Config::parse(&big(1, true)).is_ok());
    // Small frames may have the most in flight.
    let small = example_text().replacen(
        "output = \"../../out\"",
        "output = \"../../out\"\nframes_ahead = 16",
        1,
    );
    assert!(Config::parse(&small).is_ok());
}

#[test]
fn corrupt_voxel_is_fail_by_default_or_skip() {
    use dray_config::CorruptVoxel;
    let cfg = Config::parse(&example_text()).unwrap();
    assert_eq!(cfg.clients.corrupt_voxel, CorruptVoxel::Fail);
    let skip = example_text().replacen(
        "preload = false",
        "preload = false\ncorrupt_voxel = \"skip\"",
        1,
    );
    assert_eq!(
        Config::parse(&skip).unwrap().clients.corrupt_voxel,
        CorruptVoxel::Skip
    );
    assert_names(
        broken(
            "preload = false",
            "preload = false\ncorrupt_voxel = \"ignore\"",
        ),
        "corrupt_voxel",
        "unknown variant `ignore`, expected `fail` or `skip`",
    );
}

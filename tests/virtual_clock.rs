//! The virtual engine (`dray sim --virtual`): 64 clients render a
//! walkthrough on one thread with every frame complete, every pixel equal
//! to `dray render`'s, bytes conserved between stores and clients and no
//! cache over its budget; and the same run twice gives the same figures,
//! since only the cost model and the models of links and disks move the
//! clock.

mod common;

use common::*;
use dray_actors::costs::{CostModel, VirtualRun};
use dray_actors::nodes::{frame_cameras, sim_virtual, RunOptions, RunSummary};

/// A fixed cost model (calibrating would make each run's differ).
fn cost() -> CostModel {
    CostModel {
        ns_per_tile: 20_000.0,
        ns_per_primary_ray: 300.0,
        ns_per_secondary_ray: 150.0,
        ns_per_voxel_visit: 400.0,
        ns_per_decoded_byte: 2.0,
        ns_per_pixel_host: 0.0,
    }
}

/// A 256 × 192 walk of `frames` frames over a small plant, `clients`
/// clients with caches of `cache_mb`, client–store links of 100 Mbit/s
/// and 2 ms, and a store disk of 55 MB/s.
fn setup(dir: &std::path::Path, frames: u32, clients: u32, cache_mb: f64) -> dray_config::Config {
    let db = plant_db(dir, 30_000);
    let path = dir.join("walk.toml");
    write_path(&db, &path, frames);
    let links = "[links.client_store]\nlatency_ms = 2.0\nbandwidth_mbps = 100.0\n[links.store_disk]\nbandwidth_mbps = 440.0\n";
    let text = config_text(&db, &path, dir, clients, cache_mb, "", links)
        .replace("width = 96", "width = 256")
        .replace("height = 64", "height = 192");
    config(dir, &text).1
}

fn run(cfg: &dray_config::Config, keep_frames: bool) -> RunSummary {
    let opts = RunOptions {
        keep_frames,
        ..RunOptions::default()
    };
    let run = VirtualRun {
        cost: cost(),
        host_cores: None,
    };
    sim_virtual(cfg, &opts, run).unwrap()
}

#[test]
fn sixty_four_virtual_clients_finish_a_walk_exactly_and_within_their_budgets() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = setup(dir.path(), 10, 64, 3.0);
    let started = std::time::Instant::now();
    let run = run(&cfg, true);
    eprintln!(
        "64 virtual clients, 10 frames: {:.1} s of wall time, {:.3} s on the virtual clock",
        started.elapsed().as_secs_f64(),
        run.display.seconds
    );
    assert!(run.display.complete, "{:?}", run.display.stopped_early);
    assert_eq!(run.display.frames.len(), 10);
    let tiles_per_frame = (256 / 16) * (192 / 16);
    for m in &run.display.frames {
        assert_eq!(m.tiles, tiles_per_frame, "frame {}", m.frame);
    }
    assert_eq!(run.scheduler.tiles, 10 * u64::from(tiles_per_frame));
    assert_eq!(run.scheduler.reassigned, 0);

    // Every byte a store sent reached a client, and no cache outgrew its
    // budget: each client accounts and frees the voxels it shares with the
    // others as its own. (A cache goes over only by voxels its packets
    // hold at that moment, as any cache does: a few of these tens of kB.)
    let sent: u64 = run.stores.iter().map(|s| s.bytes_served).sum();
    let received: u64 = run.clients.iter().map(|c| c.bytes_fetched).sum();
    assert_eq!(sent, received);
    assert!(received > 0);
    let budget = cfg.cache_bytes();
    for (i, c) in run.clients.iter().enumerate() {
        assert!(
            c.peak_cache_bytes <= budget + budget / 10,
            "client {i}: {c:?}"
        );
    }
    assert!(run.clients.iter().map(|c| c.evicted).sum::<u64>() > 0);
    assert!(run.clients.iter().filter(|c| c.tiles > 0).count() > 1);

    // The pixels are the reference's.
    let cameras = frame_cameras(&cfg).unwrap();
    for (img, cam) in run.display.images.iter().zip(&cameras).step_by(3) {
        let (rgba, depth, primid) = reference(&cfg, cam);
        assert_eq!(img.primid.as_ref().unwrap(), &primid, "frame {}", img.frame);
        let d = img.depth.as_ref().unwrap();
        assert!(d
            .iter()
            .zip(&depth)
            .all(|(a, b)| a.to_bits() == b.to_bits()));
        assert!(img.rgba == rgba, "frame {}: colors", img.frame);
    }
}

#[test]
fn the_same_virtual_run_twice_gives_the_same_figures() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = setup(dir.path(), 6, 8, 0.3);
    let figures = |r: &RunSummary| {
        let frames: Vec<String> = r
            .display
            .frames
            .iter()
            .map(|m| {
                format!(
                    "{} {} {} {} {} {} {} {}",
                    m.frame,
                    m.frame_ms,
                    m.rays,
                    m.bytes_fetched,
                    m.misses,
                    m.stall_ms,
                    m.reassigned,
                    m.tiles_per_client
                )
            })
            .collect();
        let clients: Vec<String> = r
            .clients
            .iter()
            .map(|c| {
                format!(
                    "{} {} {} {} {}",
                    c.tiles, c.fetched, c.bytes_fetched, c.evicted, c.peak_cache_bytes
                )
            })
            .collect();
        (frames, clients, r.display.seconds)
    };
    let a = figures(&run(&cfg, false));
    let b = figures(&run(&cfg, false));
    assert_eq!(a, b);
}

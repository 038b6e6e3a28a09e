//! The centre (scheduler node and display) against many stand-in clients:
//! every frame completes, every tile is done once, and the run ends.

use dray_actors::centre::{run_centre, walk_config};
use std::sync::mpsc;
use std::time::Duration;

#[test]
fn the_centre_serves_every_tile_of_every_frame_to_many_clients() {
    let dir = tempfile::tempdir().unwrap();
    let (size, tile, frames) = ((320, 192), 16, 6);
    let cfg = walk_config(dir.path(), size, tile, frames).unwrap();
    let tiles_per_frame = u64::from((size.0 / tile) * (size.1 / tile));
    for clients in [1, 7, 300] {
        let (tx, rx) = mpsc::channel();
        let cfg = cfg.clone();
        std::thread::spawn(move || tx.send(run_centre(&cfg, clients)));
        let run = rx
            .recv_timeout(Duration::from_secs(60))
            .unwrap_or_else(|_| panic!("{clients} clients: no end after 60 s"))
            .unwrap_or_else(|e| panic!("{clients} clients: {e}"));
        assert_eq!(run.clients, clients);
        assert_eq!(run.frames, frames as usize, "{run:?}");
        assert_eq!(run.tiles, tiles_per_frame * u64::from(frames), "{run:?}");
        // Nothing is reassigned (every answer is immediate): at most one
        // assignment a tile, and a report for each.
        assert!(run.scheduler_sent <= run.tiles, "{run:?}");
        assert!(run.scheduler_received > run.scheduler_sent, "{run:?}");
    }
}

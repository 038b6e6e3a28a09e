//! What the centre (the scheduler node and the display) costs as clients
//! grow: for each client count, a walk of `--frames` frames at
//! `--width` × `--height` served by that many stand-in clients that answer
//! every tile at once (`dray_actors::centre`). Prints a Markdown table and,
//! with `--csv`, one row per run.
//!
//!   cargo run --release -p dray-bench --bin bench-centre
//!   cargo run --release -p dray-bench --bin bench-centre -- --clients 1,64,1024 --frames 20
//!
//! The client count at which the scheduler becomes the bottleneck follows
//! from its messages per CPU second: a client that renders `R` tiles per
//! second costs the scheduler three messages a tile (its request, the
//! assignment, the display's report), so one core serves
//! `messages_per_s / (3 R)` such clients.

use anyhow::Context;
use clap::Parser;
use dray_actors::centre::{run_centre, walk_config, CentreRun};
use std::path::PathBuf;

#[derive(Parser)]
#[command(about = "The scheduler's and the display's cost per frame as clients grow")]
struct Args {
    /// Client counts, comma separated.
    #[arg(long, value_delimiter = ',', default_values_t = [1usize, 4, 16, 64, 256, 1024])]
    clients: Vec<usize>,
    /// Frames of the walk.
    #[arg(long, default_value_t = 30)]
    frames: u32,
    /// Image width, pixels.
    #[arg(long, default_value_t = 1920)]
    width: u32,
    /// Image height, pixels.
    #[arg(long, default_value_t = 1088)]
    height: u32,
    /// Tile side, pixels.
    #[arg(long, default_value_t = 32)]
    tile_size: u32,
    /// Tiles a client renders per second, for the bottleneck column.
    #[arg(long, default_value_t = 1000.0)]
    client_tiles_per_s: f64,
    /// Appends one CSV row per run here.
    #[arg(long)]
    csv: Option<PathBuf>,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let dir = tempfile::tempdir()?;
    let cfg = walk_config(
        dir.path(),
        (args.width, args.height),
        args.tile_size,
        args.frames,
    )?;
    let tiles = args.width.div_ceil(args.tile_size) * args.height.div_ceil(args.tile_size);
    // One row per run, its header only in a new file.
    let mut csv = match &args.csv {
        Some(p) => {
            let new = !p.exists();
            let f = std::fs::OpenOptions::new()
                .create(true)
                .append(true)
                .open(p)
                .with_context(|| format!("opening {}", p.display()))?;
            Some(csv::WriterBuilder::new().has_headers(new).from_writer(f))
        }
        None => None,
    };
    println!(
        "{} × {} px, {tiles} tiles of {} px a frame, {} frames; stand-in clients answer at once",
        args.width, args.height, args.tile_size, args.frames
    );
    println!();
    println!("| clients | frames/s | scheduler CPU ms/frame | display CPU ms/frame | assignments/frame | scheduler msgs per CPU s | clients one scheduler core serves at {} tiles/s each |", args.client_tiles_per_s);
    println!("|---:|---:|---:|---:|---:|---:|---:|");
    for &n in &args.clients {
        let r: CentreRun =
            run_centre(&cfg, n).with_context(|| format!("the run with {n} clients"))?;
        let serves = r.scheduler_messages_per_cpu_s() / (3.0 * args.client_tiles_per_s);
        println!(
            "| {} | {:.1} | {:.2} | {:.2} | {:.0} | {:.0} | {:.0} |",
            n,
            r.fps,
            r.scheduler_ms_per_frame(),
            r.display_ms_per_frame(),
            r.scheduler_sent as f64 / r.frames as f64,
            r.scheduler_messages_per_cpu_s(),
            serves
        );
        if let Some(w) = csv.as_mut() {
            w.serialize(&r)?;
            w.flush()?;
        }
    }
    Ok(())
}

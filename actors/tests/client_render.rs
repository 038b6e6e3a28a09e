//! The Client end to end against a real store and a fake scheduler and
//! display: the frame it renders tile by tile, fetching voxels over a link
//! of 5 ms latency into a cache of any size, equals `dray render`'s frame
//! with every voxel resident, bit for bit, in suspend and block mode.
//!
//! These run on the real clock: the render threads are OS threads, which
//! tokio's paused clock would not wait for.

mod client_common;

use client_common::*;
use dray_actors::client::{run_client, ClientOptions, ClientSummary};
use dray_actors::names;
use dray_actors::Shard;
use dray_protocol::{Compression, Message, Shutdown};
use dray_runtime::{InProcNet, LinkShape, Role};
use dray_trace::render::Isa;
use dray_trace::tile::MissMode;
use std::time::Duration;

const LATENCY: Duration = Duration::from_millis(5);
const THREADS: usize = 2;
const TILES_AHEAD: usize = 2;

struct Run {
    out: Assembled,
    summary: ClientSummary,
}

fn options(cache_bytes: u64, mode: MissMode, stores: usize) -> ClientOptions {
    ClientOptions {
        threads: THREADS,
        cache_bytes,
        miss_mode: mode,
        max_inflight_fetches: 4,
        tiles_ahead: TILES_AHEAD,
        max_tiles_ahead: TILES_AHEAD,
        preload: false,
        pixel_compression: Compression::Lz4,
        isa: Isa::detect(),
        stores: routes(stores),
        scheduler: names::scheduler(),
        display: names::display(),
        corrupt_voxel: Default::default(),
        virtual_clock: None,
    }
}

/// One client renders the test frame from one store.
async fn run(db: &Db, cache_bytes: u64, mode: MissMode, hint: bool, outage: bool) -> Run {
    run_with(db, options(cache_bytes, mode, 1), hint, outage).await
}

/// The same with any client options.
async fn run_with(db: &Db, opts: ClientOptions, hint: bool, outage: bool) -> Run {
    let capacity = opts.threads + opts.tiles_ahead;
    let r = render_once(db, opts, hint, outage, false, 0).await;
    // One slot a finished tile, besides the first ones.
    assert!(
        r.out.requested <= capacity + 24,
        "the client asked for {} tiles, for 24 with {capacity} at once",
        r.out.requested
    );
    r
}

/// One client renders the test frame against a real store (5 ms away)
/// and the fake front end, which hands out as many tiles as the client
/// may hold (`threads + max_tiles_ahead`). With `outage`, the store is cut
/// off mid-frame and brought back; with `far_scheduler`, the scheduler is
/// 5 ms away too. The frame is sample `sample` of the camera.
async fn render_once(
    db: &Db,
    opts: ClientOptions,
    hint: bool,
    outage: bool,
    far_scheduler: bool,
    sample: u32,
) -> Run {
    let capacity = opts.threads + opts.max_tiles_ahead;
    let net = InProcNet::new();
    let (_store_bus, store) = start_store(&net, 0, db.path.clone(), Shard::ALL);
    let mut fe = FakeFrontEnd::new(&net);
    fe.sample = sample;
    let client_bus = net.add_node(names::client_node(0), Role::Client).unwrap();
    let shape = LinkShape {
        latency: LATENCY,
        ..LinkShape::default()
    };
    net.set_shape(&names::client_node(0), &names::store_node(0), shape)
        .unwrap();
    if far_scheduler {
        net.set_shape(&names::client_node(0), fe.scheduler_bus.node(), shape)
            .unwrap();
    }
    let mb = client_bus.mailbox(name(names::CLIENT), 1024).unwrap();
    let client = tokio::spawn(run_client(mb, opts));
    let cut = outage.then(|| {
        let net = net.clone();
        tokio::spawn(async move {
            // Cut the store off while fetches are in flight, then bring it
            // back: unanswered fetches must be sent again.
            tokio::time::sleep(Duration::from_millis(60)).await;
            net.disconnect(&names::client_node(0), &names::store_node(0));
            tokio::time::sleep(Duration::from_millis(150)).await;
            net.reconnect(&names::client_node(0), &names::store_node(0));
            tokio::time::Instant::now()
        })
    });
    let out = render_frame(&mut fe, &db.db, &names::client(0), capacity, hint).await;
    let finished = tokio::time::Instant::now();
    let summary = tokio::time::timeout(Duration::from_secs(30), client)
        .await
        .expect("the client stops when told")
        .unwrap()
        .unwrap();
    if let Some(cut) = cut {
        let back = cut.await.unwrap();
        assert!(
            finished > back,
            "the frame was done before the store came back"
        );
    }
    fe.display
        .send(
            &names::store(0),
            Message::Shutdown(Shutdown {
                reason: "test over".into(),
            }),
        )
        .await
        .unwrap();
    let served = store.await.unwrap().unwrap();
    assert!(served.served >= summary.fetched);
    assert_eq!(summary.tiles, 24);
    eprintln!("{summary:?}");
    Run { out, summary }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn suspend_mode_with_a_cache_of_three_voxels_equals_the_reference() {
    let db = plant_db(20_000);
    let want = reference(&db.db);
    let budget = 3 * mean_voxel_bytes(&db.db);
    let r = run(&db, budget, MissMode::Suspend, false, false).await;
    assert_same(&r.out, &want, "suspend, small cache");
    let s = &r.summary;
    assert!(s.evicted > 0, "{s:?}");
    assert!(s.refetched > 0, "{s:?}");
    assert!(s.misses > 0 && s.rays > 0, "{s:?}");
    // The tiles report the voxels they missed, fewer than they touched.
    let o = &r.out;
    assert!(
        o.misses > 0 && o.misses <= o.touched,
        "{} of {}",
        o.misses,
        o.touched
    );
    assert_eq!(s.prefetched, 0);
}

/// A jittered sample (every ray moved within its pixel), its voxels
/// fetched into a small cache, equals `dray render`'s frame of that sample.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_jittered_sample_equals_the_reference_of_that_sample() {
    let db = plant_db(20_000);
    let want = reference_sample(&db.db, 3);
    assert_ne!(want.depth, reference(&db.db).depth, "the rays moved");
    let budget = 3 * mean_voxel_bytes(&db.db);
    let opts = options(budget, MissMode::Suspend, 1);
    let r = render_once(&db, opts, false, false, false, 3).await;
    assert_same(&r.out, &want, "sample 3, small cache");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn suspend_mode_with_a_big_cache_fetches_each_voxel_once() {
    let db = plant_db(20_000);
    let want = reference(&db.db);
    let r = run(&db, 1 << 30, MissMode::Suspend, false, false).await;
    assert_same(&r.out, &want, "suspend, big cache");
    let s = &r.summary;
    assert_eq!(s.evicted, 0, "{s:?}");
    assert_eq!(s.refetched, 0, "{s:?}");
    assert!(s.fetched > 0 && s.fetched <= db.db.manifest.voxels.len() as u64);
    assert!(s.peak_cache_bytes > 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tiles_sent_in_batches_equal_the_reference() {
    // 8 tiles ahead: finished tiles leave 4 at a time (and the frame's
    // last ones at once), and the client asks for 4 tiles at a time.
    let db = plant_db(20_000);
    let want = reference(&db.db);
    let budget = 3 * mean_voxel_bytes(&db.db);
    let opts = ClientOptions {
        tiles_ahead: 8,
        max_tiles_ahead: 8,
        ..options(budget, MissMode::Suspend, 1)
    };
    let r = run_with(&db, opts, false, false).await;
    assert_same(&r.out, &want, "batches, small cache");
    assert!(
        r.out.max_outstanding > THREADS + TILES_AHEAD,
        "tiles were asked ahead"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_preloaded_client_fetches_nothing_for_its_tiles() {
    let db = plant_db(20_000);
    let want = reference(&db.db);
    let voxels = db.db.manifest.voxels.len() as u64;
    let opts = ClientOptions {
        preload: true,
        ..options(1 << 30, MissMode::Suspend, 1)
    };
    let r = run_with(&db, opts, false, false).await;
    assert_same(&r.out, &want, "preloaded");
    let s = &r.summary;
    assert_eq!((s.preloaded, s.fetched), (voxels, voxels), "{s:?}");
    assert_eq!(s.misses, 0, "{s:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_whose_threads_run_dry_asks_for_more_tiles_ahead() {
    // Every voxel preloaded, so a tile traces in well under the 10 ms round
    // trip to the scheduler: asking one tile ahead, the threads finish
    // their tiles and wait. The client then asks for more ahead, and the
    // frame is still the reference, bit for bit.
    let db = plant_db(20_000);
    let want = reference(&db.db);
    let opts = ClientOptions {
        preload: true,
        tiles_ahead: 1,
        max_tiles_ahead: 16,
        ..options(1 << 30, MissMode::Suspend, 1)
    };
    // The fake scheduler hands out whatever the client may hold.
    let Run { out, summary } = render_once(&db, opts, false, false, true, 0).await;
    assert_same(&out, &want, "tiles asked ahead as the threads ran dry");
    assert_eq!(summary.tiles, 24);
    // The fake scheduler hands out only what was asked for, so holding
    // more than the first request's tiles means the client asked for more
    // ahead. (How many it asked for in all depends on when it grew: this
    // also required more than 27, and failed about one run in three when
    // the growth came late in the frame.)
    assert!(
        out.max_outstanding > THREADS + 1,
        "the client held at most {} tiles and asked for {} in all: it never asked for more ahead",
        out.max_outstanding,
        out.requested
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_preload_stops_at_the_cache_budget() {
    let db = plant_db(20_000);
    let want = reference(&db.db);
    let budget = 3 * mean_voxel_bytes(&db.db);
    let opts = ClientOptions {
        preload: true,
        ..options(budget, MissMode::Suspend, 1)
    };
    let r = run_with(&db, opts, false, false).await;
    assert_same(&r.out, &want, "preload into a small cache");
    let s = &r.summary;
    // The budget is counted in decoded sizes, which are below the
    // prepared sizes the cache counts: a few more than 3 may be asked for.
    let voxels = db.db.manifest.voxels.len() as u64;
    assert!(
        s.preloaded > 0 && s.preloaded < voxels / 4,
        "{s:?} of {voxels} voxels"
    );
    assert!(s.misses > 0, "{s:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn block_mode_with_a_cache_of_three_voxels_equals_the_reference() {
    let db = plant_db(20_000);
    let want = reference(&db.db);
    let budget = 3 * mean_voxel_bytes(&db.db);
    let r = run(&db, budget, MissMode::Block, false, false).await;
    assert_same(&r.out, &want, "block, small cache");
    assert!(r.summary.evicted > 0, "{:?}", r.summary);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn block_mode_with_a_big_cache_equals_the_reference() {
    let db = plant_db(20_000);
    let want = reference(&db.db);
    let r = run(&db, 1 << 30, MissMode::Block, false, false).await;
    assert_same(&r.out, &want, "block, big cache");
    assert_eq!(r.summary.refetched, 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hinted_voxels_are_prefetched() {
    let db = plant_db(20_000);
    let want = reference(&db.db);
    let r = run(&db, 1 << 30, MissMode::Suspend, true, false).await;
    assert_same(&r.out, &want, "prefetch");
    let s = &r.summary;
    assert!(s.prefetched > 0, "{s:?}");
    assert!(s.fetched <= db.db.manifest.voxels.len() as u64, "{s:?}");
    assert_eq!(s.refetched, 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_store_outage_mid_frame_is_survived() {
    let db = plant_db(20_000);
    let want = reference(&db.db);
    let budget = 3 * mean_voxel_bytes(&db.db);
    let r = run(&db, budget, MissMode::Suspend, false, true).await;
    assert_same(&r.out, &want, "store outage");
}

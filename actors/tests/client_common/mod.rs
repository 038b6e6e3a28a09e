//! Helpers shared by the store and client tests: a small generated plant
//! preprocessed into a temporary database, nodes of an in-process network,
//! and a fake scheduler and display that hand out every tile of a frame
//! and assemble what comes back.
#![allow(dead_code)]

use dray_actors::names::{self, StoreRoutes};
use dray_actors::settings::kernel_settings;
use dray_actors::store::{run_store, StoreOptions, StoreSummary};
use dray_actors::{ActorError, Shard};
use dray_protocol::{
    AssignTile, Camera as WireCamera, Message, PrefetchHint, Reflective, RenderSettings, Shutdown,
    TileRect,
};
use dray_runtime::{Bus, Delivery, InProcNet, Mailbox, Name, Role};
use dray_scene::db::Database;
use dray_trace::accel::{ResidentSource, TopLevel};
use dray_trace::camera::Camera;
use dray_trace::render::{render_sample, Frame, Isa};
use std::path::PathBuf;
use std::time::Duration;
use tokio::task::JoinHandle;

pub use dray_testkit::TestDb as Db;

/// A plant of `triangles` triangles, at most 512 per voxel.
pub fn plant_db(triangles: u64) -> Db {
    dray_testkit::plant_db(triangles, 5, 512)
}

pub fn name(s: &str) -> Name {
    Name::new(s).unwrap()
}

/// Starts store `index` of the network on `db` with `shard`.
pub fn start_store(
    net: &InProcNet,
    index: usize,
    db: PathBuf,
    shard: Shard,
) -> (Bus, JoinHandle<Result<StoreSummary, ActorError>>) {
    let bus = net.add_node(names::store_node(index), Role::Store).unwrap();
    let mb = bus.mailbox(name(names::STORE), 1024).unwrap();
    let h = tokio::spawn(run_store(
        mb,
        StoreOptions {
            database: db,
            shard,
            max_concurrent: 2,
            disk: Default::default(),
        },
    ));
    (bus, h)
}

/// The shading every end-to-end test uses: shaded, shadows, one mirror
/// bounce, depth and ids returned.
pub fn wire_settings() -> RenderSettings {
    RenderSettings {
        shade: true,
        shadows: true,
        reflection_depth: 1,
        light_dir: [0.3, 1.0, 0.2],
        reflective: Reflective::All,
        reflectance: 0.4,
        voxel_colors: false,
        want_depth: true,
        want_prim_ids: true,
    }
}

pub const WIDTH: u32 = 96;
pub const HEIGHT: u32 = 64;
pub const TILE: u32 = 16;

pub fn camera(db: &Database) -> Camera {
    Camera::default_for(&db.manifest.model_bounds, WIDTH, HEIGHT)
}

pub fn wire_camera(c: &Camera) -> WireCamera {
    WireCamera {
        eye: c.eye.to_array(),
        look: c.look.to_array(),
        up: c.up.to_array(),
        fov_y_deg: c.fov_degrees,
    }
}

/// The frame `dray render` gives, every voxel resident.
pub fn reference(db: &Database) -> Frame {
    reference_sample(db, 0)
}

/// The frame of sample `sample` ([`render_sample`]), every voxel resident.
pub fn reference_sample(db: &Database, sample: u32) -> Frame {
    let top = TopLevel::from_manifest(&db.manifest);
    let source = ResidentSource::load(db).unwrap();
    let settings = kernel_settings(
        &wire_settings(),
        db.manifest.model_bounds.diagonal(),
        2,
        Isa::detect(),
    );
    render_sample(&top, &source, &camera(db), sample, &settings).unwrap()
}

/// Average prepared size of a voxel.
pub fn mean_voxel_bytes(db: &Database) -> u64 {
    let source = ResidentSource::load(db).unwrap();
    source.bytes() as u64 / db.manifest.voxels.len() as u64
}

/// The nodes and mailboxes of a fake scheduler and display.
pub struct FakeFrontEnd {
    pub scheduler_bus: Bus,
    pub scheduler: Mailbox,
    pub display: Mailbox,
    /// The sample of the camera the frames are (0 unless set).
    pub sample: u32,
}

impl FakeFrontEnd {
    pub fn new(net: &InProcNet) -> FakeFrontEnd {
        let scheduler_bus = net.add_node(name("scheduler"), Role::Scheduler).unwrap();
        let display_bus = net.add_node(name("display"), Role::Display).unwrap();
        FakeFrontEnd {
            scheduler: scheduler_bus.mailbox(name(names::SCHEDULER), 1024).unwrap(),
            display: display_bus.mailbox(name(names::DISPLAY), 1024).unwrap(),
            scheduler_bus,
            sample: 0,
        }
    }
}

/// What the fake front end collected.
pub struct Assembled {
    pub rgba: Vec<[u8; 4]>,
    pub depth: Vec<f32>,
    pub primid: Vec<u32>,
    pub max_outstanding: usize,
    /// Tiles the client asked for in all.
    pub requested: usize,
    /// The tiles' misses and voxels touched, summed.
    pub misses: u64,
    pub touched: u64,
}

/// Hands out every 16×16 tile of a 96×64 frame on demand (as many as the
/// client asked for, never more), assembles the TileDone messages, and
/// tells the client to stop when every tile is in. With `hint`, sends
/// the client a prefetch hint naming every voxel when it first asks for
/// work.
///
/// A tile asked for is handed out only once `capacity` (the client's
/// tiles in progress and ahead) allows it by the tiles whose pixels have
/// arrived: the client sends a tile's pixels before it asks again, but
/// they travel to the display's mailbox and may arrive after the request
/// reaches the scheduler's (counting by arrival, a correct client
/// sometimes seemed to hold one tile too many).
pub async fn render_frame(
    fe: &mut FakeFrontEnd,
    db: &Database,
    client: &dray_protocol::Address,
    capacity: usize,
    mut hint: bool,
) -> Assembled {
    let cam = camera(db);
    let mut tiles: Vec<TileRect> = Vec::new();
    for y in (0..HEIGHT).step_by(TILE as usize) {
        for x in (0..WIDTH).step_by(TILE as usize) {
            tiles.push(TileRect {
                x,
                y,
                w: TILE,
                h: TILE,
            });
        }
    }
    tiles.reverse();
    let total = tiles.len();
    let n = (WIDTH * HEIGHT) as usize;
    let mut out = Assembled {
        rgba: vec![[0; 4]; n],
        depth: vec![f32::NAN; n],
        primid: vec![0xdead_beef; n],
        max_outstanding: 0,
        requested: 0,
        misses: 0,
        touched: 0,
    };
    // Asked for, handed out so far, and asked for but not yet allowed.
    let (mut granted, mut pending) = (0usize, 0usize);
    let mut slots = 0usize;
    let mut outstanding = 0usize;
    let mut done = 0usize;
    let mut hit_samples = 0usize;
    let deadline = tokio::time::Instant::now() + Duration::from_secs(120);
    while done < total {
        let allowed = (done + capacity).saturating_sub(granted).min(pending);
        (slots, pending, granted) = (slots + allowed, pending - allowed, granted + allowed);
        while slots > 0 && !tiles.is_empty() {
            let tile = tiles.pop().unwrap();
            slots -= 1;
            outstanding += 1;
            out.max_outstanding = out.max_outstanding.max(outstanding);
            fe.scheduler
                .send(
                    client,
                    Message::AssignTile(AssignTile {
                        frame: 7,
                        tile,
                        camera: wire_camera(&cam),
                        width: WIDTH,
                        height: HEIGHT,
                        settings: wire_settings(),
                        sample: fe.sample,
                    }),
                )
                .await
                .unwrap();
        }
        let d = tokio::select! {
            // The client sends a tile's pixels before it asks for the next
            // tile: take them first, so in-progress tiles are counted right.
            biased;
            d = fe.display.recv() => d,
            d = fe.scheduler.recv() => d,
            _ = tokio::time::sleep_until(deadline) => panic!("frame not done in time: {done} of {total} tiles"),
        };
        if let Delivery::Message { msg, .. } = d.expect("bus gone") {
            match msg {
                Message::RequestWork(r) => {
                    if std::mem::take(&mut hint) {
                        // The client is up: hint at every voxel.
                        let ids: Vec<u32> = (0..db.manifest.voxels.len() as u32).collect();
                        fe.scheduler
                            .send(
                                client,
                                Message::PrefetchHint(PrefetchHint {
                                    frame: 0,
                                    voxels: dray_protocol::PackedU32(ids),
                                }),
                            )
                            .await
                            .unwrap();
                    }
                    out.requested += r.slots as usize;
                    pending += r.slots as usize;
                }
                Message::TileDone(t) => {
                    assert_eq!(t.frame, 7);
                    assert!(t.stats.rays >= (TILE * TILE) as u64);
                    // Misses count voxels, as voxels_touched does: the
                    // hit rate 1 - misses / touched is a rate.
                    assert!(t.stats.misses <= t.stats.voxels_touched, "{:?}", t.stats);
                    out.misses += u64::from(t.stats.misses);
                    out.touched += u64::from(t.stats.voxels_touched);
                    hit_samples += t.hits.as_slice().len();
                    outstanding -= 1;
                    done += 1;
                    let r = t.tile;
                    let depth = t.depth.expect("depth asked for").0;
                    let ids = t.prim_ids.expect("ids asked for").0;
                    let rgba = t.pixels.decode(r.area()).expect("pixels").to_rgba();
                    for row in 0..r.h {
                        for col in 0..r.w {
                            let k = (row * r.w + col) as usize;
                            let p = ((r.y + row) * WIDTH + r.x + col) as usize;
                            out.rgba[p] = rgba[k];
                            out.depth[p] = depth[k];
                            out.primid[p] = ids[k];
                        }
                    }
                }
                other => panic!("unexpected {other:?}"),
            }
        }
    }
    assert!(hit_samples > 0, "the tiles carry their hit samples");
    fe.display
        .send(
            client,
            Message::Shutdown(Shutdown {
                reason: "test over".into(),
            }),
        )
        .await
        .unwrap();
    out
}

/// Asserts the assembled frame equals the reference bit for bit.
pub fn assert_same(got: &Assembled, want: &Frame, what: &str) {
    let mut hits = 0;
    for p in 0..(WIDTH * HEIGHT) as usize {
        let (x, y) = (p as u32 % WIDTH, p as u32 / WIDTH);
        assert_eq!(
            got.primid[p], want.primid[p],
            "{what}: id of pixel ({x}, {y})"
        );
        assert_eq!(
            got.depth[p].to_bits(),
            want.depth[p].to_bits(),
            "{what}: depth of pixel ({x}, {y})"
        );
        assert_eq!(
            got.rgba[p], want.rgba[p],
            "{what}: color of pixel ({x}, {y})"
        );
        hits += (want.primid[p] != u32::MAX) as usize;
    }
    assert!(
        hits > (WIDTH * HEIGHT) as usize / 10,
        "{what}: only {hits} pixels hit: the test sees too little"
    );
}

/// Routes to the stores `0..count`, shard `i/count` each.
pub fn routes(count: usize) -> StoreRoutes {
    StoreRoutes::new(
        (0..count)
            .map(|i| {
                (
                    Shard {
                        index: i as u32,
                        count: count as u32,
                    },
                    names::store(i),
                )
            })
            .collect(),
    )
    .unwrap()
}

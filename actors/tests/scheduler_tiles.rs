//! The scheduler and the frame assigner against fake clients and a fake
//! display on the in-process network, on tokio's paused clock.

use dray_actors::names;
use dray_actors::scheduler::{
    run_assigner, run_scheduler, AssignerOptions, SchedulerOptions, SchedulerSummary, TileGrid,
    TilePolicy, MAX_QUEUED_FRAMES,
};
use dray_protocol::{
    AssignTile, BoundedVec, Camera, CameraUpdate, FrameAssigned, FrameDone, LinkBytes, Message,
    Name, Reflective, RenderSettings, RequestWork, Role, Shutdown, TileOwners, TileRect,
    TileReport, TileStats,
};
use dray_runtime::{Bus, InProcNet, Mailbox};
use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::task::JoinHandle;

fn settings() -> RenderSettings {
    RenderSettings {
        shade: true,
        shadows: false,
        reflection_depth: 0,
        light_dir: [1.0, 1.0, 1.0],
        reflective: Reflective::All,
        reflectance: 0.5,
        voxel_colors: false,
        want_depth: false,
        want_prim_ids: false,
    }
}

fn camera(k: u64) -> Camera {
    Camera {
        eye: [k as f32, 1.0, 5.0],
        look: [0.0, 0.0, 0.0],
        up: [0.0, 1.0, 0.0],
        fov_y_deg: 50.0,
    }
}

fn name(s: &str) -> Name {
    Name::new(s).unwrap()
}

#[derive(Clone, Debug, PartialEq)]
enum Event {
    Assigned {
        frame: u64,
        tile: TileRect,
        client: usize,
    },
    Reported {
        frame: u64,
        tile: TileRect,
        client: usize,
    },
}

type Log = Arc<Mutex<Vec<Event>>>;

/// How a fake client behaves.
#[derive(Clone)]
struct Behaviour {
    slots: u16,
    /// Time to render a tile (sleep on the paused clock; a block of tiles
    /// takes this for each of its tiles of 32 pixels).
    render: Duration,
    /// The `time_us` it reports for a tile.
    cost: fn(&TileRect) -> u64,
    /// Reports nothing of this frame and the later ones (0: never
    /// reports; `u64::MAX`: always does).
    silent_from: u64,
    /// The `misses` it reports for a tile.
    misses: u32,
    /// Reports hit positions: where its pixel rays meet the plane z = 0.
    plane_hits: bool,
    /// How many times `render` a tile of this frame takes.
    slowdown: fn(u64) -> u32,
    /// Says its cache holds the whole model.
    holds_model: bool,
}

impl Behaviour {
    fn normal() -> Behaviour {
        Behaviour {
            slots: 2,
            render: Duration::from_millis(5),
            cost: |_| 1000,
            silent_from: u64::MAX,
            misses: 1,
            plane_hits: true,
            slowdown: |_| 1,
            holds_model: false,
        }
    }
}

fn stats_for(tile: &TileRect, cost: u64, misses: u32) -> TileStats {
    TileStats {
        rays: tile.area() as u64,
        time_us: cost,
        voxels_touched: 2,
        misses,
        bytes_fetched: 10,
        bytes_raw: 30,
        stall_us: 5,
        link: LinkBytes {
            client_store: 40,
            client_scheduler: 7,
            display: 0,
            store_uplink: 35,
            client_downlink: 45,
        },
    }
}

/// A fake client: takes tiles, renders them one at a time, reports them to
/// the scheduler and asks for one more tile per tile done.
fn spawn_client(net: &InProcNet, i: usize, b: Behaviour, log: Log) -> (Bus, JoinHandle<()>) {
    let bus = net.add_node(names::client_node(i), Role::Client).unwrap();
    let mut mb = bus.mailbox(name(names::CLIENT), 1024).unwrap();
    let task = tokio::spawn(async move {
        let me = mb.handle();
        let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel::<(u64, TileRect, Vec<[f32; 3]>)>();
        let worker = {
            let me = me.clone();
            let b = b.clone();
            let log = log.clone();
            tokio::spawn(async move {
                while let Some((frame, tile, hits)) = rx.recv().await {
                    // A block takes as long as its tiles.
                    let tiles = tile.w.div_ceil(32) * tile.h.div_ceil(32);
                    tokio::time::sleep(b.render * (b.slowdown)(frame) * tiles).await;
                    if frame >= b.silent_from {
                        continue;
                    }
                    log.lock().unwrap().push(Event::Reported {
                        frame,
                        tile,
                        client: i,
                    });
                    let report = TileReport {
                        client: names::client_node(i),
                        frame,
                        tile,
                        stats: stats_for(&tile, (b.cost)(&tile), b.misses),
                        hits: BoundedVec::new(hits).unwrap(),
                    };
                    if me
                        .send(&names::scheduler(), Message::TileReport(report))
                        .await
                        .is_err()
                    {
                        return;
                    }
                    let _ = me
                        .send(
                            &names::scheduler(),
                            Message::RequestWork(RequestWork {
                                slots: 1,
                                holds_model: b.holds_model,
                            }),
                        )
                        .await;
                }
            })
        };
        let _ = me
            .send(
                &names::scheduler(),
                Message::RequestWork(RequestWork {
                    slots: b.slots,
                    holds_model: b.holds_model,
                }),
            )
            .await;
        while let Some((_, msg)) = mb.recv_message().await {
            match msg {
                Message::AssignTile(a) => {
                    log.lock().unwrap().push(Event::Assigned {
                        frame: a.frame,
                        tile: a.tile,
                        client: i,
                    });
                    let hits = if b.plane_hits {
                        plane_hits(&a)
                    } else {
                        Vec::new()
                    };
                    let _ = tx.send((a.frame, a.tile, hits));
                }
                Message::Shutdown(_) => break,
                _ => {}
            }
        }
        worker.abort();
    });
    (bus, task)
}

/// Where the rays of a 4 × 4 grid of the tile's pixels meet the plane
/// z = 0 (the scene of the reprojection test).
fn plane_hits(a: &AssignTile) -> Vec<[f32; 3]> {
    let b = dray_actors::settings::kernel_camera(&a.camera, a.width, a.height).basis();
    let t = a.tile;
    let mut hits = Vec::new();
    for j in 0..4 {
        for i in 0..4 {
            let d = b.direction(t.x + (2 * i + 1) * t.w / 8, t.y + (2 * j + 1) * t.h / 8);
            let s = -b.eye.z / d.z;
            if s > 0.0 {
                hits.push((b.eye + d * s).to_array());
            }
        }
    }
    hits
}

struct Cluster {
    net: InProcNet,
    _sched_bus: Bus,
    scheduler: JoinHandle<SchedulerSummary>,
    assigner: JoinHandle<()>,
    display: Mailbox,
    _display_bus: Bus,
    prefetcher: Mailbox,
    log: Log,
    clients: Vec<(Bus, JoinHandle<()>)>,
}

const W: u32 = 100;
const H: u32 = 70;

/// Single tiles: these tests follow each tile (blocks of tiles have
/// tests of their own at the end).
fn options(affinity: bool, deadline: Duration) -> SchedulerOptions {
    SchedulerOptions {
        tile_size: 32,
        max_block_px: 0,
        policy: if affinity {
            TilePolicy::Affinity
        } else {
            TilePolicy::Random
        },
        costliest_first: true,
        tile_deadline: deadline,
        display: names::display(),
        assigner: names::assigner(),
        prefetcher: Some(names::prefetcher()),
        seed: 7,
    }
}

fn cluster(opts: SchedulerOptions, width: u32, height: u32, clients: &[Behaviour]) -> Cluster {
    let net = InProcNet::new();
    let sched_bus = net.add_node(name("scheduler"), Role::Scheduler).unwrap();
    let smb = sched_bus.mailbox(name(names::SCHEDULER), 4096).unwrap();
    let amb = sched_bus.mailbox(name(names::ASSIGNER), 1024).unwrap();
    // The test plays the prefetcher: it collects the tile owners.
    let prefetcher = sched_bus.mailbox(name(names::PREFETCHER), 1024).unwrap();
    let display_bus = net.add_node(name("display"), Role::Display).unwrap();
    let display = display_bus.mailbox(name(names::DISPLAY), 1024).unwrap();
    let scheduler = tokio::spawn(async move { run_scheduler(smb, opts).await.unwrap() });
    let assigner = tokio::spawn(async move {
        run_assigner(
            amb,
            AssignerOptions {
                scheduler: names::scheduler(),
                prefetcher: Some(names::prefetcher()),
                width,
                height,
                settings: settings(),
            },
        )
        .await
        .unwrap()
    });
    let log: Log = Arc::default();
    let clients = clients
        .iter()
        .enumerate()
        .map(|(i, b)| spawn_client(&net, i, b.clone(), log.clone()))
        .collect();
    Cluster {
        net,
        _sched_bus: sched_bus,
        scheduler,
        assigner,
        display,
        _display_bus: display_bus,
        prefetcher,
        log,
        clients,
    }
}

impl Cluster {
    async fn send_camera(&self, seq: u64, camera: Camera) {
        self.display
            .send(
                &names::assigner(),
                Message::CameraUpdate(CameraUpdate {
                    seq,
                    camera,
                    sample: 0,
                    format: None,
                }),
            )
            .await
            .unwrap();
    }

    async fn camera(&self, k: u64) {
        self.display
            .send(
                &names::assigner(),
                Message::CameraUpdate(CameraUpdate {
                    seq: k,
                    camera: camera(k),
                    sample: 0,
                    format: None,
                }),
            )
            .await
            .unwrap();
    }

    async fn frame_done(&mut self) -> FrameDone {
        let got = tokio::time::timeout(Duration::from_secs(600), self.display.recv_message())
            .await
            .expect("a frame completes");
        match got {
            Some((_, Message::FrameDone(d))) => d,
            other => panic!("display got {other:?}"),
        }
    }

    /// Runs frames `0..n`, each camera update sent after the previous frame
    /// is done (a display waiting for each frame).
    async fn run_sequential(&mut self, n: u64) -> Vec<FrameDone> {
        let mut done = Vec::new();
        for k in 0..n {
            self.camera(k).await;
            let d = self.frame_done().await;
            assert_eq!(d.frame, k);
            done.push(d);
        }
        done
    }

    async fn stop(self) -> SchedulerSummary {
        let bye = || {
            Message::Shutdown(Shutdown {
                reason: "test over".into(),
            })
        };
        self.display.send(&names::assigner(), bye()).await.unwrap();
        self.display.send(&names::scheduler(), bye()).await.unwrap();
        self.assigner.await.unwrap();
        let s = self.scheduler.await.unwrap();
        for (_, task) in self.clients {
            task.abort();
        }
        s
    }

    fn events(&self) -> Vec<Event> {
        self.log.lock().unwrap().clone()
    }

    /// Per frame, per tile index, the clients it was assigned to.
    fn assignments(&self, frame: u64) -> HashMap<usize, Vec<usize>> {
        let grid = TileGrid::new(W, H, 32);
        self.assignments_in(frame, &grid)
    }

    fn assignments_in(&self, frame: u64, grid: &TileGrid) -> HashMap<usize, Vec<usize>> {
        let mut m: HashMap<usize, Vec<usize>> = HashMap::new();
        for e in self.events() {
            if let Event::Assigned {
                frame: f,
                tile,
                client,
            } = e
            {
                if f == frame {
                    m.entry(grid.index_of(&tile).expect("a grid tile"))
                        .or_default()
                        .push(client);
                }
            }
        }
        m
    }
}

/// Four clients whose tiles' hits lie on the plane z = 0.
fn plane_clients() -> [Behaviour; 4] {
    [(); 4].map(|_| Behaviour {
        plane_hits: true,
        ..Behaviour::normal()
    })
}

#[tokio::test(start_paused = true)]
async fn scheduler_assigns_every_tile_once_and_double_buffers() {
    assigns_every_tile_once_and_double_buffers(false).await;
}

/// The same with affinity, where a client that has run through its own
/// tiles of a frame may release the next one early (and work ahead on its
/// own tiles there).
#[tokio::test(start_paused = true)]
async fn scheduler_with_affinity_assigns_every_tile_once_and_double_buffers() {
    assigns_every_tile_once_and_double_buffers(true).await;
}

async fn assigns_every_tile_once_and_double_buffers(affinity: bool) {
    let mut c = cluster(
        options(affinity, Duration::from_secs(60)),
        W,
        H,
        &[Behaviour::normal(), Behaviour::normal()],
    );
    // All cameras up front: the assigner paces the frames.
    let frames = 5u64;
    for k in 0..frames {
        c.camera(k).await;
    }
    let grid = TileGrid::new(W, H, 32);
    let n = grid.count() as u32;
    for k in 0..frames {
        let d = c.frame_done().await;
        assert_eq!(d.frame, k, "frames complete in order here");
        let s = &d.stats;
        assert_eq!(s.tiles, n);
        assert_eq!(s.reassigned, 0);
        assert_eq!(s.rays, u64::from(W * H));
        assert_eq!(s.misses, u64::from(n));
        assert_eq!(s.bytes_fetched, 10 * u64::from(n));
        assert_eq!(s.bytes_raw, 30 * u64::from(n));
        assert_eq!(s.voxels_touched, 2 * u64::from(n));
        assert_eq!(s.stall_us, 5 * u64::from(n));
        assert_eq!(s.link.client_store, 40 * u64::from(n));
        assert_eq!(s.link.client_downlink, 45 * u64::from(n));
        assert!(s.time_us > 0);
        let per: Vec<_> = s.clients.as_slice().to_vec();
        assert_eq!(per.iter().map(|c| c.tiles).sum::<u32>(), n);
        assert_eq!(per.iter().map(|c| c.rays).sum::<u64>(), u64::from(W * H));
        assert_eq!(per.len(), 2, "both clients rendered: {per:?}");
        // Every tile once, to exactly one client.
        let a = c.assignments(k);
        assert_eq!(a.len(), grid.count());
        assert!(a.values().all(|v| v.len() == 1), "frame {k}: {a:?}");
    }
    // The prefetcher got every camera update and every frame's owners.
    let mut cams = Vec::new();
    let mut owners: Vec<TileOwners> = Vec::new();
    while let Some(d) = c.prefetcher.try_recv() {
        if let dray_runtime::Delivery::Message { msg, .. } = d {
            match msg {
                Message::CameraUpdate(u) => cams.push(u.seq),
                Message::TileOwners(o) => owners.push(o),
                _ => {}
            }
        }
    }
    assert_eq!(cams, (0..frames).collect::<Vec<_>>());
    assert_eq!(owners.len() as u64, frames);
    for o in &owners {
        assert_eq!((o.width, o.height, o.tile_size), (W, H, 32));
        assert_eq!(o.owners.0.len(), grid.count());
        assert!(o
            .owners
            .0
            .iter()
            .all(|&i| (i as usize) < o.clients.as_slice().len()));
    }
    // Double buffering: frame k+1's first tile goes out before frame k's
    // last report, and only once frame k is fully assigned.
    let ev = c.events();
    for k in 0..frames - 1 {
        let first_next = ev
            .iter()
            .position(|e| matches!(e, Event::Assigned { frame, .. } if *frame == k + 1))
            .unwrap();
        let last_report = ev
            .iter()
            .rposition(|e| matches!(e, Event::Reported { frame, .. } if *frame == k))
            .unwrap();
        let last_assign = ev
            .iter()
            .rposition(|e| matches!(e, Event::Assigned { frame, .. } if *frame == k))
            .unwrap();
        assert!(
            first_next < last_report,
            "frame {} started only after frame {k} was done",
            k + 1
        );
        assert!(
            affinity || last_assign < first_next,
            "frame {} started before frame {k} was fully assigned",
            k + 1
        );
    }
    // Nothing more arrives: one FrameDone per frame.
    tokio::time::sleep(Duration::from_secs(5)).await;
    assert!(c.display.try_recv().is_none());
    let s = c.stop().await;
    assert_eq!(s.frames, frames);
    assert_eq!(s.tiles, frames * u64::from(n));
    assert_eq!(s.reassigned, 0);
}

/// Share of the tiles of frame `b` that went to the client that had them in
/// frame `a`.
fn overlap(c: &Cluster, grid: &TileGrid, a: u64, b: u64) -> f64 {
    let (fa, fb) = (c.assignments_in(a, grid), c.assignments_in(b, grid));
    let same = (0..grid.count())
        .filter(|i| fa.get(i).map(|v| v[0]) == fb.get(i).map(|v| v[0]))
        .count();
    same as f64 / grid.count() as f64
}

async fn affinity_overlap(affinity: bool) -> (f64, f64) {
    let (w, h) = (256, 256);
    let mut c = cluster(
        options(affinity, Duration::from_secs(60)),
        w,
        h,
        &[Behaviour::normal(), Behaviour::normal()],
    );
    let grid = TileGrid::new(w, h, 32);
    c.run_sequential(4).await;
    let r = (overlap(&c, &grid, 1, 2), overlap(&c, &grid, 2, 3));
    // Both clients did a fair share.
    let f2 = c.assignments_in(2, &grid);
    let first = f2.values().filter(|v| v[0] == 0).count();
    assert!(
        (16..=48).contains(&first),
        "client 0 got {first} of 64 tiles"
    );
    c.stop().await;
    r
}

#[tokio::test(start_paused = true)]
async fn scheduler_affinity_keeps_tiles_with_their_client() {
    let (a12, a23) = affinity_overlap(true).await;
    assert!(a12 >= 0.9 && a23 >= 0.9, "affinity: {a12} {a23}");
    let (r12, r23) = affinity_overlap(false).await;
    assert!(
        (0.25..=0.75).contains(&r12) && (0.25..=0.75).contains(&r23),
        "random: {r12} {r23}"
    );
}

fn costly(t: &TileRect) -> u64 {
    // Tile (48, 16) of a 64×64 image in 16-pixel tiles (index 7) is by far
    // the costliest; the others vary.
    if (t.x, t.y) == (48, 16) {
        1_000_000
    } else {
        u64::from((t.x * 31 + t.y * 17) % 97) + 10
    }
}

#[tokio::test(start_paused = true)]
async fn scheduler_hands_out_the_costliest_tile_first() {
    let one = Behaviour {
        slots: 1,
        cost: costly,
        ..Behaviour::normal()
    };
    let opts = SchedulerOptions {
        tile_size: 16,
        ..options(true, Duration::from_secs(60))
    };
    let mut c = cluster(opts, 64, 64, &[one]);
    c.run_sequential(2).await;
    let order = |frame: u64| -> Vec<TileRect> {
        c.events()
            .into_iter()
            .filter_map(|e| match e {
                Event::Assigned { frame: f, tile, .. } if f == frame => Some(tile),
                _ => None,
            })
            .collect()
    };
    let grid = TileGrid::new(64, 64, 16);
    // No history: along the curve, each tile next to the one before.
    let ranks = grid.curve_ranks();
    let f0: Vec<u32> = order(0)
        .iter()
        .map(|t| ranks[grid.index_of(t).unwrap()])
        .collect();
    assert_eq!(f0, (0..16).collect::<Vec<_>>());
    // Then by the last frame's cost, costliest first.
    let f1 = order(1);
    assert_eq!((f1[0].x, f1[0].y), (48, 16));
    let costs: Vec<u64> = f1.iter().map(costly).collect();
    assert!(costs.windows(2).all(|w| w[0] >= w[1]), "{costs:?}");
    c.stop().await;
}

#[tokio::test(start_paused = true)]
async fn scheduler_reassigns_the_tiles_of_a_lost_client() {
    let mute = Behaviour {
        slots: 4,
        silent_from: 0,
        ..Behaviour::normal()
    };
    let mut c = cluster(
        options(true, Duration::from_secs(3600)),
        W,
        H,
        &[Behaviour::normal(), mute],
    );
    c.camera(0).await;
    // Wait until the mute client holds tiles, then cut it off.
    tokio::time::timeout(Duration::from_secs(60), async {
        loop {
            let held = c
                .events()
                .iter()
                .filter(|e| matches!(e, Event::Assigned { client: 1, .. }))
                .count();
            if held >= 4 {
                break;
            }
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
    })
    .await
    .expect("the mute client got 4 tiles");
    c.net.disconnect(&name("scheduler"), &names::client_node(1));
    let d = c.frame_done().await;
    let n = TileGrid::new(W, H, 32).count() as u32;
    assert_eq!(d.stats.tiles, n);
    assert_eq!(d.stats.reassigned, 4);
    let per = d.stats.clients.as_slice();
    assert_eq!(per.len(), 1);
    assert_eq!((per[0].node.as_str(), per[0].tiles), ("client-0", n));
    // The next frame goes to the survivor alone.
    c.camera(1).await;
    let d = c.frame_done().await;
    assert_eq!((d.frame, d.stats.reassigned), (1, 0));
    let s = c.stop().await;
    assert_eq!((s.frames, s.reassigned), (2, 4));
}

#[tokio::test(start_paused = true)]
async fn scheduler_reassigns_after_the_deadline_and_ignores_late_reports() {
    // Client 1 is connected but takes 10 s per tile; the deadline is 200 ms.
    let slow = Behaviour {
        slots: 2,
        render: Duration::from_secs(10),
        ..Behaviour::normal()
    };
    let mut c = cluster(
        options(true, Duration::from_millis(200)),
        W,
        H,
        &[Behaviour::normal(), slow],
    );
    let started = tokio::time::Instant::now();
    c.camera(0).await;
    let d = c.frame_done().await;
    let n = TileGrid::new(W, H, 32).count() as u32;
    assert_eq!(d.stats.tiles, n);
    assert_eq!(d.stats.reassigned, 2, "the slow client's two tiles");
    assert!(d.stats.time_us >= 200_000, "{}", d.stats.time_us);
    assert!(started.elapsed() < Duration::from_secs(5));
    let per = d.stats.clients.as_slice();
    assert_eq!((per.len(), per[0].tiles), (1, n));
    // The slow client's reports come in long after: ignored, no second
    // FrameDone, and the next frame still completes.
    tokio::time::sleep(Duration::from_secs(30)).await;
    assert!(c.display.try_recv().is_none());
    c.camera(1).await;
    let d = c.frame_done().await;
    assert_eq!(d.frame, 1);
    assert_eq!(d.stats.tiles, n);
    let tiles: u32 = d.stats.clients.as_slice().iter().map(|c| c.tiles).sum();
    assert_eq!(tiles, n);
    c.stop().await;
}

async fn next(mb: &mut Mailbox) -> Option<Message> {
    tokio::time::timeout(Duration::from_secs(1), mb.recv_message())
        .await
        .ok()
        .flatten()
        .map(|(_, m)| m)
}

/// The assigner alone: the test plays the scheduler and the prefetcher.
#[tokio::test(start_paused = true)]
async fn assigner_releases_one_frame_at_a_time_and_drops_the_oldest() {
    let net = InProcNet::new();
    let bus = net.add_node(name("scheduler"), Role::Scheduler).unwrap();
    let amb = bus.mailbox(name(names::ASSIGNER), 1024).unwrap();
    let mut sched = bus.mailbox(name(names::SCHEDULER), 1024).unwrap();
    let mut pre = bus.mailbox(name(names::PREFETCHER), 1024).unwrap();
    let dbus = net.add_node(name("display"), Role::Display).unwrap();
    let display = dbus.mailbox(name(names::DISPLAY), 1024).unwrap();
    let task = tokio::spawn(run_assigner(
        amb,
        AssignerOptions {
            scheduler: names::scheduler(),
            prefetcher: Some(names::prefetcher()),
            width: 64,
            height: 48,
            settings: settings(),
        },
    ));
    let update = |seq: u64| {
        Message::CameraUpdate(CameraUpdate {
            seq,
            camera: camera(seq),
            sample: 0,
            format: None,
        })
    };
    for seq in [0, 1, 1, 0, 2] {
        display.send(&names::assigner(), update(seq)).await.unwrap();
    }
    let start = |m: Option<Message>| match m {
        Some(Message::FrameStart(f)) => f,
        other => panic!("expected a frame start, got {other:?}"),
    };
    let f0 = start(next(&mut sched).await);
    assert_eq!((f0.frame, f0.width, f0.height), (0, 64, 48));
    assert_eq!(f0.camera, camera(0));
    // Nothing more until frame 0 is assigned.
    assert!(next(&mut sched).await.is_none());
    let assigned = |frame| Message::FrameAssigned(FrameAssigned { frame });
    // A FrameAssigned for another frame changes nothing.
    sched.send(&names::assigner(), assigned(5)).await.unwrap();
    assert!(next(&mut sched).await.is_none());
    sched.send(&names::assigner(), assigned(0)).await.unwrap();
    assert_eq!(start(next(&mut sched).await).frame, 1);
    sched.send(&names::assigner(), assigned(1)).await.unwrap();
    assert_eq!(start(next(&mut sched).await).frame, 2);
    // The prefetcher saw each new update once.
    let mut seen = Vec::new();
    while let Some(Message::CameraUpdate(u)) = next(&mut pre).await {
        seen.push(u.seq);
    }
    assert_eq!(seen, vec![0, 1, 2]);
    // A burst while frame 2 is being assigned: only the newest 64 wait.
    let burst = 3..3 + MAX_QUEUED_FRAMES as u64 + 10;
    for seq in burst.clone() {
        display.send(&names::assigner(), update(seq)).await.unwrap();
    }
    let mut released = Vec::new();
    let mut last = 2;
    loop {
        sched
            .send(&names::assigner(), assigned(last))
            .await
            .unwrap();
        match next(&mut sched).await {
            Some(Message::FrameStart(f)) => {
                released.push(f.frame);
                last = f.frame;
            }
            None => break,
            Some(other) => panic!("{other:?}"),
        }
    }
    let want: Vec<u64> = (burst.end - MAX_QUEUED_FRAMES as u64..burst.end).collect();
    assert_eq!(released, want);
    display
        .send(
            &names::assigner(),
            Message::Shutdown(Shutdown {
                reason: "done".into(),
            }),
        )
        .await
        .unwrap();
    task.await.unwrap().unwrap();
}

#[tokio::test(start_paused = true)]
async fn scheduler_affinity_holds_with_double_buffering() {
    // Cameras all sent at once: frame k+1 is handed out while frame k
    // renders, by the owners of the last frame done.
    let (w, h) = (256, 256);
    let mut c = cluster(
        options(true, Duration::from_secs(60)),
        w,
        h,
        &[Behaviour::normal(), Behaviour::normal()],
    );
    for k in 0..6 {
        c.camera(k).await;
    }
    for _ in 0..6 {
        c.frame_done().await;
    }
    let grid = TileGrid::new(w, h, 32);
    for k in 2..5 {
        let o = overlap(&c, &grid, k, k + 1);
        assert!(o >= 0.9, "frames {k} and {}: {o}", k + 1);
    }
    c.stop().await;
}

/// Share of the pairs of side-by-side tiles of `frame` that went to the
/// same client: 1 when each client's tiles are one compact region, about
/// 1/clients when they are scattered.
fn neighbours_together(c: &Cluster, grid: &TileGrid, frame: u64) -> f64 {
    let owner = c.assignments_in(frame, grid);
    let (cols, rows) = (grid.cols as usize, grid.rows as usize);
    let (mut same, mut pairs) = (0, 0);
    for y in 0..rows {
        for x in 0..cols {
            let i = y * cols + x;
            for j in [
                (x + 1 < cols).then_some(i + 1),
                (y + 1 < rows).then_some(i + cols),
            ]
            .into_iter()
            .flatten()
            {
                pairs += 1;
                same += usize::from(owner[&i][0] == owner[&j][0]);
            }
        }
    }
    same as f64 / pairs as f64
}

#[tokio::test(start_paused = true)]
async fn scheduler_affinity_gives_each_client_a_compact_region() {
    // Clients of different speeds: the fast ones take tiles beyond their
    // own every frame, which must come from their regions' borders.
    let speeds = [3, 5, 7, 9].map(|ms| Behaviour {
        render: Duration::from_millis(ms),
        ..Behaviour::normal()
    });
    let (w, h) = (640, 480);
    let grid = TileGrid::new(w, h, 32);
    for affinity in [true, false] {
        let mut c = cluster(options(affinity, Duration::from_secs(60)), w, h, &speeds);
        c.run_sequential(6).await;
        for k in 0..6 {
            let together = neighbours_together(&c, &grid, k);
            if affinity {
                assert!(together >= 0.8, "affinity, frame {k}: {together}");
            } else {
                assert!(together <= 0.45, "random, frame {k}: {together}");
            }
        }
        if affinity {
            for k in 1..5 {
                let o = overlap(&c, &grid, k, k + 1);
                assert!(o >= 0.75, "frames {k} and {}: {o}", k + 1);
            }
        }
        c.stop().await;
    }
}

/// Walking towards what it shows, the camera sees content stream outward
/// from the image's centre; each client keeps a sector around the centre,
/// so the content keeps its client on its way out. Tiles along a line out
/// of the centre share their client, and a tile goes to the client that
/// had, a frame before, the tile its content came from.
#[tokio::test(start_paused = true)]
async fn scheduler_affinity_gives_clients_sectors_while_the_camera_walks_forward() {
    let four = plane_clients();
    let (w, h) = (640, 480);
    let grid = TileGrid::new(w, h, 32);
    let mut c = cluster(options(true, Duration::from_secs(60)), w, h, &four);
    // The plane z = 0, from 10 down to 6.5 away.
    let dist = |k: u64| 10.0 - 0.7 * k as f32;
    for k in 0..6u64 {
        let camera = Camera {
            eye: [0.0, 0.0, dist(k)],
            look: [0.0, 0.0, 0.0],
            up: [0.0, 1.0, 0.0],
            fov_y_deg: 50.0,
        };
        c.send_camera(k, camera).await;
        assert_eq!(c.frame_done().await.frame, k);
    }
    let (cx, cy) = (w as f32 / 2.0, h as f32 / 2.0);
    let centre = |i: usize| {
        let r = grid.rect(i);
        (r.x as f32 + r.w as f32 / 2.0, r.y as f32 + r.h as f32 / 2.0)
    };
    for k in 2..6 {
        let (a, b) = (c.assignments_in(k - 1, &grid), c.assignments_in(k, &grid));
        let (mut radial, mut radial_all, mut kept, mut kept_all) = (0, 0, 0, 0);
        for (&i, owner) in &b {
            let (x, y) = centre(i);
            // Twice as far out along the same line.
            if let Some(j) =
                grid.tile_at((cx + 2.0 * (x - cx)) as u32, (cy + 2.0 * (y - cy)) as u32)
            {
                radial_all += 1;
                radial += usize::from(b[&j][0] == owner[0]);
            }
            // Where this tile's content was a frame before.
            let s = dist(k) / dist(k - 1);
            let j = grid
                .tile_at((cx + (x - cx) * s) as u32, (cy + (y - cy) * s) as u32)
                .unwrap();
            kept_all += 1;
            kept += usize::from(a[&j][0] == owner[0]);
        }
        let (radial, kept) = (
            radial as f64 / radial_all as f64,
            kept as f64 / kept_all as f64,
        );
        assert!(
            radial >= 0.85,
            "frame {k}: {radial} of radial neighbours share their client"
        );
        assert!(
            kept >= 0.8,
            "frame {k}: {kept} of the tiles follow their content"
        );
    }
    c.stop().await;
}

#[tokio::test(start_paused = true)]
async fn scheduler_affinity_follows_content_that_moves_across_the_screen() {
    // The camera pans along x over the plane z = 0 by 8 tiles' worth of
    // the image per frame: tile (x, y) of frame k + 1 shows what tile
    // (x + 8, y) showed in frame k, and should go to the client that
    // rendered that (by screen position alone about 0.3 do). Some move
    // anyway: the clients whose content leaves the screen take tiles from
    // those whose content stays.
    let four = plane_clients();
    let (w, h) = (640, 480);
    let grid = TileGrid::new(w, h, 32);
    let per_frame = 8.0 * 32.0 / h as f32 * 2.0 * 5.0 * 25f32.to_radians().tan();
    let mut c = cluster(options(true, Duration::from_secs(60)), w, h, &four);
    for k in 0..6u64 {
        let x = k as f32 * per_frame;
        let camera = Camera {
            eye: [x, 0.0, 5.0],
            look: [x, 0.0, 0.0],
            up: [0.0, 1.0, 0.0],
            fov_y_deg: 50.0,
        };
        c.send_camera(k, camera).await;
        assert_eq!(c.frame_done().await.frame, k);
    }
    for k in 1..5 {
        let (a, b) = (c.assignments_in(k, &grid), c.assignments_in(k + 1, &grid));
        let cols = grid.cols as usize;
        let (mut same, mut all) = (0, 0);
        for (i, owner) in &b {
            if i % cols + 8 < cols {
                all += 1;
                same += usize::from(a[&(i + 8)][0] == owner[0]);
            }
        }
        let share = same as f64 / all as f64;
        assert!(share >= 0.7, "frames {k} and {}: {share}", k + 1);
    }
    c.stop().await;
}

#[tokio::test(start_paused = true)]
async fn scheduler_takes_tile_reports_from_the_display_but_not_from_strangers() {
    // Client 0 takes tiles and never reports them; the display, which
    // has the pixels, does. A third client's reports about client 0's
    // tiles are not believed.
    let silent = Behaviour {
        silent_from: 0,
        slots: 64,
        ..Behaviour::normal()
    };
    let mut c = cluster(options(true, Duration::from_secs(600)), W, H, &[silent]);
    let stranger_bus = c.net.add_node(names::client_node(9), Role::Client).unwrap();
    let stranger = stranger_bus.mailbox(name(names::CLIENT), 16).unwrap();
    c.camera(0).await;
    let grid = TileGrid::new(W, H, 32);
    // Every tile handed out to client 0 (it asked for more than all).
    for _ in 0..100 {
        if c.assignments_in(0, &grid).len() == grid.count() {
            break;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    assert_eq!(c.assignments_in(0, &grid).len(), grid.count());
    let report = |i: usize| {
        Message::TileReport(TileReport {
            client: names::client_node(0),
            frame: 0,
            tile: grid.rect(i),
            stats: stats_for(&grid.rect(i), 1000, 1),
            hits: BoundedVec::default(),
        })
    };
    for i in 0..grid.count() {
        stranger.send(&names::scheduler(), report(i)).await.unwrap();
    }
    let waited = tokio::time::timeout(Duration::from_secs(30), c.frame_done()).await;
    assert!(waited.is_err(), "a stranger's reports completed the frame");
    for i in 0..grid.count() {
        c.display
            .send(&names::scheduler(), report(i))
            .await
            .unwrap();
    }
    assert_eq!(c.frame_done().await.frame, 0);
    let s = c.stop().await;
    assert_eq!((s.frames, s.reassigned), (1, 0));
}

/// Sends `frames` cameras at once, all the same, and waits for every
/// frame to complete, in order.
async fn fly_standing_still(c: &mut Cluster, frames: u64) {
    let still = Camera {
        eye: [0.0, 0.0, 5.0],
        look: [0.0, 0.0, 0.0],
        up: [0.0, 1.0, 0.0],
        fov_y_deg: 50.0,
    };
    for k in 0..frames {
        c.send_camera(k, still).await;
    }
    for k in 0..frames {
        assert_eq!(c.frame_done().await.frame, k);
    }
}

#[tokio::test(start_paused = true)]
async fn scheduler_affinity_works_ahead_on_own_tiles_before_taking_anothers() {
    // Two clients, equally fast except that client 1 is eight times slower
    // in frames 2 and 4 (another program took its core); the camera stands
    // still and every camera is sent at once. When client 0 has run
    // through its own tiles of such a frame, it goes on with its own tiles
    // of the next frame (released early for it) instead of taking client
    // 1's, which would fetch what its cache lacks: before its first tile
    // of frame k + 1 it takes at most its two slots' worth of the tiles
    // that client 1 rendered in frame k - 1.
    let hiccup = Behaviour {
        slowdown: |frame| if frame == 2 || frame == 4 { 8 } else { 1 },
        ..Behaviour::normal()
    };
    let (w, h) = (256, 256);
    let mut c = cluster(
        options(true, Duration::from_secs(60)),
        w,
        h,
        &[Behaviour::normal(), hiccup],
    );
    fly_standing_still(&mut c, 6).await;
    let grid = TileGrid::new(w, h, 32);
    let events = c.events();
    for k in [2, 4] {
        let before = c.assignments_in(k - 1, &grid);
        let slow_had = |tile: &TileRect| {
            let i = grid.index_of(tile).expect("a grid tile");
            before.get(&i).is_some_and(|v| v[0] == 1)
        };
        let mut taken = 0;
        for e in &events {
            if let Event::Assigned {
                frame,
                tile,
                client: 0,
            } = e
            {
                if *frame == k + 1 {
                    break;
                }
                taken += usize::from(*frame == k && slow_had(tile));
            }
        }
        let slow_tiles = before.values().filter(|v| v[0] == 1).count();
        assert!(
            slow_tiles >= 8 && taken <= 2,
            "frame {k}: the fast client took {taken} of the slow one's {slow_tiles} tiles first"
        );
    }
    c.stop().await;
}

#[tokio::test(start_paused = true)]
async fn scheduler_affinity_lets_a_client_with_a_queue_take_no_others_tiles() {
    // As above, but client 0 asks for 16 tiles at once: when client 1
    // falls behind, client 0 takes client 1's tiles only once it holds at
    // most one tile. A client with a queue of its own has no need of them,
    // and each fetches what its cache lacks.
    let deep = Behaviour {
        slots: 16,
        ..Behaviour::normal()
    };
    let hiccup = Behaviour {
        slowdown: |frame| if frame >= 2 { 8 } else { 1 },
        ..Behaviour::normal()
    };
    let (w, h) = (256, 256);
    let mut c = cluster(
        options(true, Duration::from_secs(60)),
        w,
        h,
        &[deep, hiccup],
    );
    fly_standing_still(&mut c, 6).await;
    let grid = TileGrid::new(w, h, 32);
    let previous: Vec<_> = (0..6).map(|k| c.assignments_in(k, &grid)).collect();
    let mut held = 0i64;
    let (mut taken, mut most) = (0, 0);
    for e in c.events() {
        match e {
            Event::Assigned {
                frame,
                tile,
                client: 0,
            } => {
                let i = grid.index_of(&tile).expect("a grid tile");
                let ones = frame > 0
                    && previous[frame as usize - 1]
                        .get(&i)
                        .is_some_and(|v| v[0] == 1);
                if ones {
                    taken += 1;
                    most = most.max(held);
                }
                held += 1;
            }
            Event::Reported { client: 0, .. } => held -= 1,
            _ => {}
        }
    }
    assert!(taken > 0, "client 0 never helped: the test sees nothing");
    assert!(
        most <= 1,
        "client 0 took one of client 1's tiles while holding {most}"
    );
    c.stop().await;
}

/// Per tile of `grid`, the clients frame `frame`'s assignments (single
/// tiles or blocks of them) gave it to, and the assignments' sizes in
/// tiles, in order.
fn blocks_in(c: &Cluster, grid: &TileGrid, frame: u64) -> (HashMap<usize, Vec<usize>>, Vec<usize>) {
    let mut tiles: HashMap<usize, Vec<usize>> = HashMap::new();
    let mut sizes = Vec::new();
    for e in c.events() {
        if let Event::Assigned {
            frame: f,
            tile,
            client,
        } = e
        {
            if f == frame {
                let b = grid.tiles_of(&tile).expect("whole tiles of the grid");
                sizes.push(b.len());
                for i in b {
                    tiles.entry(i).or_default().push(client);
                }
            }
        }
    }
    (tiles, sizes)
}

/// Options with blocks of up to 4 × 4 tiles of 32 pixels.
fn block_options(deadline: Duration) -> SchedulerOptions {
    SchedulerOptions {
        max_block_px: 128,
        ..options(true, deadline)
    }
}

/// The sizes, in tiles, of the assignments `client` got in `frame`.
fn blocks_of(c: &Cluster, grid: &TileGrid, frame: u64, client: usize) -> Vec<usize> {
    c.events()
        .iter()
        .filter_map(|e| match e {
            Event::Assigned {
                frame: f,
                client: k,
                tile,
            } if *f == frame && *k == client => grid.tiles_of(tile).map(|b| b.len()),
            _ => None,
        })
        .collect()
}

/// Clients whose tiles find everything in their caches.
fn warm() -> Behaviour {
    Behaviour {
        misses: 0,
        ..Behaviour::normal()
    }
}

#[tokio::test(start_paused = true)]
async fn scheduler_hands_out_blocks_of_tiles_early_and_single_tiles_last() {
    let (w, h) = (640, 480);
    let opts = block_options(Duration::from_secs(60));
    let mut c = cluster(opts, w, h, &[warm(), warm()]);
    let done = c.run_sequential(4).await;
    let grid = TileGrid::new(w, h, 32);
    let n = grid.count();
    for (k, d) in done.iter().enumerate() {
        let (tiles, sizes) = blocks_in(&c, &grid, k as u64);
        // Every tile once, to exactly one client.
        assert_eq!(tiles.len(), n, "frame {k}");
        assert!(tiles.values().all(|v| v.len() == 1), "frame {k}");
        if k == 0 {
            // No frame before it: nothing is known to render without a
            // miss, and the tiles go one by one.
            assert!(sizes.iter().all(|&s| s == 1), "{sizes:?}");
        } else {
            // Blocks of up to 4 × 4 tiles where a block's tiles all stay
            // with one client, single tiles last, far fewer assignments
            // than tiles.
            assert!(sizes.contains(&16), "frame {k}: {sizes:?}");
            assert!(sizes.iter().all(|&s| s <= 16), "frame {k}: {sizes:?}");
            assert_eq!(sizes[sizes.len() - 1], 1, "frame {k}: {sizes:?}");
            assert!(
                sizes.len() < n / 4,
                "frame {k}: {} assignments",
                sizes.len()
            );
        }
        // A block counts as its tiles.
        let s = &d.stats;
        assert_eq!(s.tiles as usize, n);
        assert_eq!(s.reassigned, 0);
        assert_eq!(s.rays, u64::from(w * h));
        let per = s.clients.as_slice();
        assert_eq!(per.iter().map(|c| c.tiles as usize).sum::<usize>(), n);
        assert_eq!(per.len(), 2, "both clients rendered: {per:?}");
    }
    // The camera moves a little each frame: each client keeps most of its
    // region, block by block.
    let kept = |a: u64, b: u64| {
        let (ta, tb) = (blocks_in(&c, &grid, a).0, blocks_in(&c, &grid, b).0);
        (0..n).filter(|i| ta[i] == tb[i]).count() as f64 / n as f64
    };
    for k in 1..3 {
        assert!(
            kept(k, k + 1) > 0.8,
            "frames {k}, {}: {}",
            k + 1,
            kept(k, k + 1)
        );
    }
    // The prefetcher's owners are per tile, with at most MAX_TILE_HITS
    // hits each.
    let mut owners: Vec<TileOwners> = Vec::new();
    while let Some(d) = c.prefetcher.try_recv() {
        if let dray_runtime::Delivery::Message {
            msg: Message::TileOwners(o),
            ..
        } = d
        {
            owners.push(o);
        }
    }
    assert_eq!(owners.len(), 4);
    for o in &owners {
        assert_eq!(o.owners.0.len(), n);
        assert!(o.owners.0.iter().all(|&i| i < 2));
        assert!(o.hit_counts.0.iter().any(|&h| h > 0));
    }
    c.stop().await;
}

#[tokio::test(start_paused = true)]
async fn scheduler_hands_out_single_tiles_where_the_last_frame_missed() {
    // Clients whose every tile meets a voxel they lack: slow, uneven
    // tiles, shared one by one.
    let (w, h) = (640, 480);
    let opts = block_options(Duration::from_secs(60));
    let mut c = cluster(opts, w, h, &[Behaviour::normal(), Behaviour::normal()]);
    c.run_sequential(3).await;
    let grid = TileGrid::new(w, h, 32);
    for k in 0..3 {
        let (tiles, sizes) = blocks_in(&c, &grid, k);
        assert_eq!(tiles.len(), grid.count());
        assert!(sizes.iter().all(|&s| s == 1), "frame {k}: {sizes:?}");
    }
    c.stop().await;
}

/// Two clients walk four frames, then the camera turns a quarter round (a
/// cut: what the last frame showed is out of view), then stays there for
/// a frame. Returns the sizes of the assignments of each frame, and how
/// many tiles kept their client across the cut.
async fn walk_through_a_cut(clients: &[Behaviour]) -> (Vec<Vec<usize>>, usize) {
    let (w, h) = (640, 480);
    let opts = block_options(Duration::from_secs(60));
    let mut c = cluster(opts, w, h, clients);
    let turned = Camera {
        eye: [3.0, 1.0, 5.0],
        look: [13.0, 1.0, 5.0],
        ..camera(3)
    };
    let cameras = [camera(0), camera(1), camera(2), camera(3), turned, turned];
    for (k, cam) in cameras.iter().enumerate() {
        c.send_camera(k as u64, *cam).await;
        assert_eq!(c.frame_done().await.frame, k as u64);
    }
    let grid = TileGrid::new(w, h, 32);
    let sizes = (0..cameras.len() as u64)
        .map(|k| blocks_in(&c, &grid, k).1)
        .collect();
    let (before, after) = (blocks_in(&c, &grid, 3).0, blocks_in(&c, &grid, 4).0);
    let kept = (0..grid.count()).filter(|i| before[i] == after[i]).count();
    c.stop().await;
    (sizes, kept)
}

#[tokio::test(start_paused = true)]
async fn scheduler_treats_a_camera_cut_as_cold_and_keeps_each_clients_side() {
    let n = TileGrid::new(640, 480, 32).count();
    let (sizes, kept) = walk_through_a_cut(&[warm(), warm()]).await;
    assert!(sizes[3].contains(&16), "before the cut: {:?}", sizes[3]);
    // The last frame's tiles rendered without a miss, but they showed
    // something else: the cut frame's tiles go one by one, as cold ones.
    assert!(sizes[4].iter().all(|&s| s == 1), "the cut: {:?}", sizes[4]);
    // It continues from the cut frame: blocks again.
    assert!(sizes[5].contains(&16), "after the cut: {:?}", sizes[5]);
    // Each client keeps its part of the screen across the cut.
    assert!(kept * 5 > n * 4, "{kept} of {n} tiles kept their client");
    // Clients whose caches hold the whole model miss nothing anywhere:
    // blocks across the cut too, and the same parts of the screen.
    let whole = Behaviour {
        holds_model: true,
        ..warm()
    };
    let (sizes, kept) = walk_through_a_cut(&[whole.clone(), whole]).await;
    assert!(sizes[4].contains(&16), "the cut: {:?}", sizes[4]);
    assert!(kept * 5 > n * 4, "{kept} of {n} tiles kept their client");
}

#[tokio::test(start_paused = true)]
async fn scheduler_reassigns_each_tile_of_a_lost_clients_block() {
    let (w, h) = (640, 480);
    // Client 1 renders the first frame, then takes a block of the second
    // and goes silent.
    let mute = Behaviour {
        slots: 1,
        silent_from: 1,
        ..warm()
    };
    let opts = block_options(Duration::from_secs(3600));
    let mut c = cluster(opts, w, h, &[warm(), mute]);
    c.run_sequential(1).await;
    c.camera(1).await;
    tokio::time::timeout(Duration::from_secs(60), async {
        while !c.events().iter().any(|e| {
            matches!(
                e,
                Event::Assigned {
                    frame: 1,
                    client: 1,
                    ..
                }
            )
        }) {
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
    })
    .await
    .expect("the mute client got a block");
    let grid = TileGrid::new(w, h, 32);
    let held: usize = blocks_of(&c, &grid, 1, 1).iter().sum();
    assert!(held >= 4, "{held} tiles");
    c.net.disconnect(&name("scheduler"), &names::client_node(1));
    let d = c.frame_done().await;
    assert_eq!(d.frame, 1);
    assert_eq!(d.stats.tiles as usize, grid.count());
    assert_eq!(
        d.stats.reassigned as usize, held,
        "each of the block's tiles"
    );
    let per = d.stats.clients.as_slice();
    assert_eq!((per.len(), per[0].tiles as usize), (1, grid.count()));
    c.stop().await;
}

#[tokio::test(start_paused = true)]
async fn scheduler_gives_a_block_the_time_of_its_tiles_before_its_deadline() {
    // Client 0 takes 1 ms a tile, client 1 5 ms; the deadline is 10 ms or
    // 8 times the median tile (1 ms) for each tile of an assignment,
    // whichever is more. Client 1's blocks of 4 or 16 tiles take 20 or
    // 80 ms: late for a tile, not for 4 or 16 of them.
    fn cost(per_tile: u64) -> impl Fn(&TileRect) -> u64 {
        move |t| per_tile * u64::from(t.w.div_ceil(32) * t.h.div_ceil(32))
    }
    let quick = Behaviour {
        render: Duration::from_millis(1),
        cost: |t| cost(1000)(t),
        ..warm()
    };
    let slower = Behaviour {
        slots: 1,
        render: Duration::from_millis(5),
        cost: |t| cost(5000)(t),
        ..warm()
    };
    let opts = block_options(Duration::from_millis(10));
    let (w, h) = (640, 256);
    let mut c = cluster(opts, w, h, &[quick, slower]);
    let done = c.run_sequential(2).await;
    let grid = TileGrid::new(w, h, 32);
    let blocks_of_1 = blocks_of(&c, &grid, 1, 1);
    assert!(blocks_of_1.iter().any(|&n| n >= 4), "{blocks_of_1:?}");
    for d in &done {
        assert_eq!(d.stats.tiles as usize, grid.count());
        assert_eq!(d.stats.reassigned, 0, "frame {}: {blocks_of_1:?}", d.frame);
    }
    c.stop().await;
}

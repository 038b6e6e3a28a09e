//! One valid message of every kind, for tests of the protocol and of the
//! transports (every transport must carry each of them unchanged).

use crate::*;

fn camera() -> Camera {
    Camera {
        eye: [0.0, 1.5, -10.0],
        look: [0.0, 1.0, 0.0],
        up: [0.0, 1.0, 0.0],
        fov_y_deg: 45.0,
    }
}

/// One message of each kind in [`MessageKind::ALL`] order. The tile result
/// carries a 32×32 tile with depth and primitive ids; the voxel carries
/// `voxel_bytes` bytes.
pub fn one_of_each(voxel_bytes: usize) -> Vec<Message> {
    let tile = TileRect {
        x: 32,
        y: 64,
        w: 32,
        h: 32,
    };
    let n = tile.area();
    vec![
        Message::RequestWork(RequestWork {
            slots: 4,
            holds_model: true,
        }),
        Message::AssignTile(AssignTile {
            frame: 7,
            tile,
            camera: camera(),
            width: 640,
            height: 480,
            settings: RenderSettings {
                shade: true,
                shadows: true,
                reflection_depth: 2,
                light_dir: [0.3, 1.0, 0.2],
                reflective: Reflective::Ids { start: 10, end: 20 },
                reflectance: 0.6,
                voxel_colors: false,
                want_depth: true,
                want_prim_ids: true,
            },
            sample: 3,
        }),
        Message::TileDone(TileDone {
            frame: 7,
            tile,
            pixels: TilePixels::Rgba(Blob((0..n * 4).map(|i| (i * 7) as u8).collect())),
            depth: Some(PackedF32(
                (0..n)
                    .map(|i| if i % 5 == 0 { f32::INFINITY } else { i as f32 })
                    .collect(),
            )),
            prim_ids: Some(PackedU32(
                (0..n)
                    .map(|i| if i % 5 == 0 { u32::MAX } else { i as u32 })
                    .collect(),
            )),
            stats: TileStats {
                rays: 3072,
                time_us: 1234,
                voxels_touched: 17,
                misses: 3,
                bytes_fetched: 123_456,
                bytes_raw: 400_000,
                stall_us: 77,
                link: LinkBytes {
                    client_store: 124_000,
                    client_scheduler: 9_000,
                    display: 0,
                    store_uplink: 123_800,
                    client_downlink: 124_100,
                },
            },
            hits: BoundedVec::new(vec![[0.5, 1.5, -2.0]]).expect("one entry is under the bound"),
        }),
        Message::FetchVoxel(FetchVoxel { id: 42 }),
        Message::VoxelLoaded(VoxelLoaded {
            id: 42,
            data: Blob((0..voxel_bytes).map(|i| (i % 251) as u8).collect()),
        }),
        Message::VoxelError(VoxelError {
            id: 43,
            message: "voxel 43 failed its checksum".into(),
        }),
        Message::CameraUpdate(CameraUpdate {
            seq: 9,
            camera: camera(),
            sample: 5,
            format: Some(FrameFormat {
                width: 320,
                height: 240,
                settings: RenderSettings {
                    shade: true,
                    shadows: true,
                    reflection_depth: 1,
                    light_dir: [-0.5, 1.0, 0.0],
                    reflective: Reflective::Color([200, 200, 210]),
                    reflectance: 0.4,
                    voxel_colors: false,
                    want_depth: false,
                    want_prim_ids: false,
                },
            }),
        }),
        Message::FrameDone(FrameDone {
            frame: 7,
            stats: FrameStats {
                tiles: 300,
                reassigned: 1,
                rays: 1_000_000,
                time_us: 40_000,
                misses: 12,
                bytes_fetched: 9_999_999,
                bytes_raw: 31_000_000,
                voxels_touched: 4_000,
                stall_us: 5,
                link: LinkBytes {
                    client_store: 10_100_000,
                    client_scheduler: 1_200_000,
                    display: 3_000,
                    store_uplink: 10_000_000,
                    client_downlink: 10_050_000,
                },
                clients: BoundedVec::new(vec![ClientFrameStats {
                    node: Name::new("client-0").expect("constant name is valid"),
                    tiles: 300,
                    rays: 1_000_000,
                    misses: 12,
                    bytes_fetched: 9_999_999,
                    stall_us: 5,
                }])
                .expect("one entry is under the bound"),
            },
        }),
        Message::PrefetchHint(PrefetchHint {
            frame: 8,
            voxels: PackedU32(vec![1, 2, 3, 500, 70_000]),
        }),
        Message::Ping(Ping { seq: 1 }),
        Message::Pong(Ping { seq: 1 }),
        Message::Shutdown(Shutdown {
            reason: "test over".into(),
        }),
        Message::FetchManifest(FetchManifest {}),
        Message::ManifestData(ManifestData {
            data: Blob((0..4096).map(|i| (i % 13) as u8).collect()),
        }),
        Message::TileReport(TileReport {
            client: Name::new("client-3").expect("constant name is valid"),
            frame: 7,
            tile,
            stats: TileStats {
                rays: 1024,
                time_us: 99,
                voxels_touched: 3,
                misses: 1,
                bytes_fetched: 4_000,
                bytes_raw: 12_500,
                stall_us: 10,
                link: LinkBytes {
                    client_store: 4_100,
                    client_scheduler: 700,
                    display: 0,
                    store_uplink: 4_050,
                    client_downlink: 4_200,
                },
            },
            hits: BoundedVec::new(vec![[1.0, -2.5, 3.25], [0.0, 1e9, -7.0]])
                .expect("two entries are under the bound"),
        }),
        Message::FrameStart(FrameStart {
            frame: 8,
            camera: camera(),
            width: 640,
            height: 480,
            settings: RenderSettings {
                shade: true,
                shadows: false,
                reflection_depth: 0,
                light_dir: [0.3, 1.0, 0.2],
                reflective: Reflective::All,
                reflectance: 0.5,
                voxel_colors: true,
                want_depth: false,
                want_prim_ids: false,
            },
            sample: 2,
        }),
        Message::FrameAssigned(FrameAssigned { frame: 8 }),
        Message::TileOwners(TileOwners {
            frame: 7,
            width: 64,
            height: 64,
            tile_size: 32,
            owners: PackedU32(vec![0, 1, u32::MAX, 0]),
            clients: BoundedVec::new(vec![
                Name::new("client-0").expect("constant name is valid"),
                Name::new("client-1").expect("constant name is valid"),
            ])
            .expect("two entries are under the bound"),
            hit_counts: Blob(vec![2, 0, 0, 1]),
            hits: PackedF32(vec![1.0, 2.0, 3.0, -1.0, 0.5, 8.0, 4.0, 4.0, -4.0]),
            misses: 17,
            holds_model: BoundedVec::new(vec![
                Name::new("client-1").expect("constant name is valid")
            ])
            .expect("one entry is under the bound"),
        }),
        Message::VoxelLost(VoxelLost {
            id: 37,
            store: Name::new("store-1").expect("constant name is valid"),
            reason: "checksum mismatch (4 tries)".into(),
            skipped: false,
        }),
    ]
}

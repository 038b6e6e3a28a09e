//! Round trips, limits and robust decoding of untrusted bytes.

use dray_protocol::examples::one_of_each;
use dray_protocol::*;
use proptest::prelude::*;

fn env(msg: Message) -> Envelope {
    Envelope {
        msg,
        from: Address::parse("store-0", "store").unwrap(),
        to: Address::parse("client-12", "loader").unwrap(),
    }
}

#[test]
fn every_kind_round_trips_and_fits_its_limit() {
    let msgs = one_of_each(100_000);
    assert_eq!(msgs.len(), MessageKind::ALL.len());
    for (msg, kind) in msgs.into_iter().zip(MessageKind::ALL) {
        assert_eq!(msg.kind(), kind);
        let payload = msg.payload_len();
        let e = env(msg);
        let bytes = encode_envelope(&e).unwrap();
        // The encoder sizes its buffer by the payload: the arrays are most
        // of a large message's bytes.
        if payload > 0 {
            assert!(
                payload <= bytes.len() && bytes.len() <= payload + ENVELOPE_SLACK,
                "{kind:?}: {payload} of {}",
                bytes.len()
            );
        }
        assert_eq!(peek_kind(&bytes).unwrap(), kind);
        assert!(bytes.len() <= kind.max_wire_size());
        assert_eq!(decode_envelope(&bytes).unwrap(), e, "{kind:?}");
    }
}

#[test]
fn stream_class_limits_cover_their_kinds() {
    for kind in MessageKind::ALL {
        if kind.is_bulk() {
            assert!(kind.max_wire_size() <= BULK_FRAME_MAX);
        } else {
            assert!(kind.max_wire_size() <= CONTROL_FRAME_MAX, "{kind:?}");
        }
    }
}

#[test]
fn oversized_body_is_refused_before_decoding() {
    let mut body = vec![0u8; MessageKind::FetchVoxel.max_wire_size() + 1];
    body[0] = 3; // FetchVoxel
    assert!(matches!(
        decode_envelope(&body),
        Err(ProtocolError::Oversized {
            kind: MessageKind::FetchVoxel,
            ..
        })
    ));
}

#[test]
fn unknown_kind_and_trailing_bytes_are_refused() {
    assert_eq!(decode_envelope(&[]), Err(ProtocolError::Empty));
    assert_eq!(
        decode_envelope(&[200, 1, 2]),
        Err(ProtocolError::UnknownKind(200))
    );
    let mut bytes = encode_envelope(&env(Message::Ping(Ping { seq: 5 }))).unwrap();
    bytes.push(0);
    assert_eq!(decode_envelope(&bytes), Err(ProtocolError::Trailing(1)));
}

#[test]
fn invalid_contents_are_refused_on_both_sides() {
    let mut msgs = one_of_each(10);
    let Message::TileDone(mut t) = msgs.remove(2) else {
        panic!("third example is a tile result")
    };
    t.pixels = TilePixels::Rgb(Blob(vec![0; t.tile.area() * 3 - 1]));
    let e = env(Message::TileDone(t.clone()));
    assert!(matches!(
        encode_envelope(&e),
        Err(ProtocolError::Invalid { .. })
    ));
    // A peer that skips validation still gets refused by the receiver.
    let raw = postcard::to_stdvec(&e).unwrap();
    assert!(matches!(
        decode_envelope(&raw),
        Err(ProtocolError::Invalid { .. })
    ));
    let Message::CameraUpdate(c) = msgs.remove(5) else {
        panic!("sixth remaining example is a camera update")
    };
    let mut nan = c.clone();
    nan.camera.fov_y_deg = f32::NAN;
    let raw = postcard::to_stdvec(&env(Message::CameraUpdate(nan))).unwrap();
    assert!(matches!(
        decode_envelope(&raw),
        Err(ProtocolError::Invalid { .. })
    ));
}

/// A camera update's new frame format is checked on receipt with the
/// limits every image size has ([`check_image_side`]), and so are its
/// settings; a sample index is any u32.
#[test]
fn a_camera_update_s_format_is_checked_on_receipt() {
    let Some(Message::CameraUpdate(c)) = one_of_each(10)
        .into_iter()
        .find(|m| m.kind() == MessageKind::CameraUpdate)
    else {
        panic!("no camera update among the examples")
    };
    let format = c.format.clone().expect("the example changes the format");
    let with = |f: Option<FrameFormat>| {
        let e = env(Message::CameraUpdate(CameraUpdate {
            format: f,
            sample: u32::MAX,
            ..c.clone()
        }));
        decode_envelope(&postcard::to_stdvec(&e).unwrap()).map(|d| d.msg)
    };
    assert!(with(None).is_ok());
    let largest = FrameFormat {
        width: MAX_IMAGE_SIDE,
        height: 1,
        ..format.clone()
    };
    assert!(matches!(
        with(Some(largest.clone())),
        Ok(Message::CameraUpdate(CameraUpdate { format: Some(f), sample: u32::MAX, .. })) if f == largest
    ));
    for (width, height) in [
        (0, 480),
        (640, 0),
        (MAX_IMAGE_SIDE + 1, 480),
        (640, u32::MAX),
    ] {
        let Err(ProtocolError::Invalid { kind, reason }) = with(Some(FrameFormat {
            width,
            height,
            ..format.clone()
        })) else {
            panic!("{width}x{height} accepted")
        };
        assert_eq!(kind, MessageKind::CameraUpdate);
        let side = if width == 640 { height } else { width };
        assert!(
            reason.contains(&check_image_side(side).unwrap_err()),
            "{width}x{height}: {reason}"
        );
    }
    let mut dark = format.clone();
    dark.settings.light_dir = [0.0; 3];
    assert!(matches!(
        with(Some(dark)),
        Err(ProtocolError::Invalid { reason, .. }) if reason.contains("light direction")
    ));
}

#[test]
fn bad_names_are_refused_when_decoding() {
    // Hand-build an envelope whose sender node name has an upper-case letter.
    #[derive(serde::Serialize)]
    struct RawAddr<'a> {
        node: &'a str,
        actor: &'a str,
    }
    #[derive(serde::Serialize)]
    struct RawEnv<'a> {
        msg: Message,
        from: RawAddr<'a>,
        to: RawAddr<'a>,
    }
    let raw = postcard::to_stdvec(&RawEnv {
        msg: Message::Ping(Ping { seq: 1 }),
        from: RawAddr {
            node: "Evil",
            actor: "a",
        },
        to: RawAddr {
            node: "b",
            actor: "c",
        },
    })
    .unwrap();
    assert!(matches!(
        decode_envelope(&raw),
        Err(ProtocolError::Malformed { .. })
    ));
    assert!(Name::new("").is_err());
    assert!(Name::new("-a").is_err());
    assert!(Name::new(&"a".repeat(64)).is_err());
    assert!(Name::new("client-3").is_ok());
}

#[test]
fn handshake_round_trips_and_version_mismatch_is_clear() {
    let hello = Handshake::Hello(Hello {
        version: PROTOCOL_VERSION,
        role: Role::Client,
        node: Name::new("client-1").unwrap(),
    });
    let bytes = hello.encode().unwrap();
    assert_eq!(Handshake::decode(&bytes).unwrap(), hello);

    let other = Handshake::Welcome(Hello {
        version: PROTOCOL_VERSION + 1,
        role: Role::Scheduler,
        node: Name::new("scheduler").unwrap(),
    });
    let err = Handshake::decode(&other.encode().unwrap()).unwrap_err();
    assert_eq!(
        err,
        ProtocolError::VersionMismatch {
            ours: PROTOCOL_VERSION,
            theirs: PROTOCOL_VERSION + 1
        }
    );
    assert!(err.to_string().contains("version mismatch"));
    // A future version whose hello has a different layout after the version.
    let mut future = vec![0u8];
    future.extend_from_slice(&[99, 0xff, 0xff, 0xff]);
    assert!(matches!(
        Handshake::decode(&future),
        Err(ProtocolError::VersionMismatch { theirs: 99, .. })
    ));
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..2048)) {
        let _ = decode_envelope(&bytes);
        let _ = Handshake::decode(&bytes);
    }

    #[test]
    fn random_bytes_behind_a_valid_tag_never_panic(
        tag in 0u8..12,
        bytes in proptest::collection::vec(any::<u8>(), 0..4096),
    ) {
        let mut body = vec![tag];
        body.extend_from_slice(&bytes);
        let _ = decode_envelope(&body);
    }

    #[test]
    fn truncated_frames_are_errors(which in 0usize..12, cut in any::<prop::sample::Index>()) {
        let msg = one_of_each(300).swap_remove(which);
        let bytes = encode_envelope(&env(msg)).unwrap();
        let at = cut.index(bytes.len());
        prop_assert!(decode_envelope(&bytes[..at]).is_err());
    }

    #[test]
    fn mutated_frames_never_panic(
        which in 0usize..12,
        flips in proptest::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..8),
    ) {
        let msg = one_of_each(300).swap_remove(which);
        let mut bytes = encode_envelope(&env(msg)).unwrap();
        for (i, v) in flips {
            let at = i.index(bytes.len());
            bytes[at] = v;
        }
        if let Ok(e) = decode_envelope(&bytes) {
            // Whatever decodes is valid and re-encodes within its limit.
            prop_assert!(encode_envelope(&e).is_ok());
        }
    }
}

/// The largest value of every kind still fits its limit: longest names,
/// largest numbers, fullest lists.
#[test]
fn maximal_messages_fit_their_limits() {
    let long = |c: char| Name::new(&c.to_string().repeat(MAX_NAME_LEN)).unwrap();
    let tile = TileRect {
        x: u32::MAX - MAX_TILE_SIDE,
        y: u32::MAX - MAX_TILE_SIDE,
        w: MAX_TILE_SIDE,
        h: MAX_TILE_SIDE,
    };
    let n = tile.area();
    let camera = Camera {
        eye: [f32::MAX; 3],
        look: [f32::MIN; 3],
        up: [1.0; 3],
        fov_y_deg: 179.0,
    };
    let text = "é".repeat(MAX_TEXT_LEN / 2);
    const MAX_LINK: LinkBytes = LinkBytes {
        client_store: u64::MAX,
        client_scheduler: u64::MAX,
        display: u64::MAX,
        store_uplink: u64::MAX,
        client_downlink: u64::MAX,
    };
    let stats = TileStats {
        rays: u64::MAX,
        time_us: u64::MAX,
        voxels_touched: u32::MAX,
        misses: u32::MAX,
        bytes_fetched: u64::MAX,
        bytes_raw: u64::MAX,
        stall_us: u64::MAX,
        link: MAX_LINK,
    };
    let client = ClientFrameStats {
        node: long('c'),
        tiles: u32::MAX,
        rays: u64::MAX,
        misses: u64::MAX,
        bytes_fetched: u64::MAX,
        stall_us: u64::MAX,
    };
    let msgs = vec![
        Message::RequestWork(RequestWork {
            slots: u16::MAX,
            holds_model: false,
        }),
        Message::AssignTile(AssignTile {
            frame: u64::MAX,
            tile: TileRect {
                x: MAX_IMAGE_SIDE - MAX_TILE_SIDE,
                y: MAX_IMAGE_SIDE - MAX_TILE_SIDE,
                w: MAX_TILE_SIDE,
                h: MAX_TILE_SIDE,
            },
            camera,
            width: MAX_IMAGE_SIDE,
            height: MAX_IMAGE_SIDE,
            settings: RenderSettings {
                shade: true,
                shadows: true,
                reflection_depth: MAX_REFLECTION_DEPTH,
                light_dir: [f32::MAX; 3],
                reflective: Reflective::Color([255; 3]),
                reflectance: 1.0,
                voxel_colors: true,
                want_depth: true,
                want_prim_ids: true,
            },
            sample: u32::MAX,
        }),
        Message::TileDone(TileDone {
            frame: u64::MAX,
            tile,
            pixels: TilePixels::Rgba(Blob(vec![255; n * 4])),
            depth: Some(PackedF32(vec![f32::INFINITY; n])),
            prim_ids: Some(PackedU32(vec![u32::MAX; n])),
            stats,
            hits: BoundedVec::new(vec![[f32::MAX; 3]; MAX_REPORT_HITS]).unwrap(),
        }),
        Message::FetchVoxel(FetchVoxel { id: u32::MAX }),
        Message::VoxelLoaded(VoxelLoaded {
            id: u32::MAX,
            data: Blob(vec![1; MAX_VOXEL_BYTES]),
        }),
        Message::VoxelError(VoxelError {
            id: u32::MAX,
            message: text.clone(),
        }),
        Message::CameraUpdate(CameraUpdate {
            seq: u64::MAX,
            camera,
            sample: u32::MAX,
            format: Some(FrameFormat {
                width: MAX_IMAGE_SIDE,
                height: MAX_IMAGE_SIDE,
                settings: RenderSettings {
                    shade: true,
                    shadows: true,
                    reflection_depth: MAX_REFLECTION_DEPTH,
                    light_dir: [f32::MIN; 3],
                    reflective: Reflective::Ids {
                        start: u32::MAX - 1,
                        end: u32::MAX,
                    },
                    reflectance: 1.0,
                    voxel_colors: true,
                    want_depth: true,
                    want_prim_ids: true,
                },
            }),
        }),
        Message::FrameDone(FrameDone {
            frame: u64::MAX,
            stats: FrameStats {
                tiles: u32::MAX,
                reassigned: u32::MAX,
                rays: u64::MAX,
                time_us: u64::MAX,
                misses: u64::MAX,
                bytes_fetched: u64::MAX,
                bytes_raw: u64::MAX,
                voxels_touched: u64::MAX,
                stall_us: u64::MAX,
                link: MAX_LINK,
                clients: BoundedVec::new(vec![client; MAX_STATS_CLIENTS]).unwrap(),
            },
        }),
        Message::PrefetchHint(PrefetchHint {
            frame: u64::MAX,
            voxels: PackedU32(vec![u32::MAX; MAX_PREFETCH_IDS]),
        }),
        Message::Ping(Ping { seq: u64::MAX }),
        Message::Pong(Ping { seq: u64::MAX }),
        Message::Shutdown(Shutdown { reason: text }),
        Message::FetchManifest(FetchManifest {}),
        Message::ManifestData(ManifestData {
            data: Blob(vec![1; MAX_VOXEL_BYTES]),
        }),
        Message::TileReport(TileReport {
            client: long('r'),
            frame: u64::MAX,
            tile,
            stats,
            hits: BoundedVec::new(vec![[f32::MAX; 3]; MAX_REPORT_HITS]).unwrap(),
        }),
        Message::FrameStart(FrameStart {
            frame: u64::MAX,
            camera,
            width: MAX_IMAGE_SIDE,
            height: MAX_IMAGE_SIDE,
            settings: RenderSettings {
                shade: true,
                shadows: true,
                reflection_depth: MAX_REFLECTION_DEPTH,
                light_dir: [f32::MAX; 3],
                reflective: Reflective::Ids {
                    start: u32::MAX - 1,
                    end: u32::MAX,
                },
                reflectance: 1.0,
                voxel_colors: true,
                want_depth: true,
                want_prim_ids: true,
            },
            sample: u32::MAX,
        }),
        Message::FrameAssigned(FrameAssigned { frame: u64::MAX }),
        Message::TileOwners(TileOwners {
            frame: u64::MAX,
            width: MAX_IMAGE_SIDE,
            height: MAX_IMAGE_SIDE / 16,
            tile_size: 16,
            owners: PackedU32(vec![MAX_STATS_CLIENTS as u32 - 1; MAX_FRAME_TILES]),
            clients: BoundedVec::new(vec![long('c'); MAX_STATS_CLIENTS]).unwrap(),
            hit_counts: Blob(vec![MAX_TILE_HITS as u8; MAX_FRAME_TILES]),
            hits: PackedF32(vec![f32::MAX; MAX_FRAME_TILES * MAX_TILE_HITS * 3]),
            misses: u64::MAX,
            holds_model: BoundedVec::new(vec![long('h'); MAX_STATS_CLIENTS]).unwrap(),
        }),
    ];
    for msg in msgs {
        let kind = msg.kind();
        let e = Envelope {
            msg,
            from: Address::new(long('a'), long('b')),
            to: Address::new(long('d'), long('e')),
        };
        let bytes = encode_envelope(&e).unwrap_or_else(|err| panic!("{kind:?}: {err}"));
        assert!(bytes.len() <= kind.max_wire_size());
        assert_eq!(decode_envelope(&bytes).unwrap(), e);
    }
    // One more item than allowed is refused by the sender.
    let too_many = Message::PrefetchHint(PrefetchHint {
        frame: 0,
        voxels: PackedU32(vec![0; MAX_PREFETCH_IDS + 1]),
    });
    assert!(encode_envelope(&env(too_many)).is_err());
}

#[test]
fn the_alpn_names_the_protocol_version() {
    assert_eq!(ALPN, format!("dray/{PROTOCOL_VERSION}").as_bytes());
}

#[test]
fn each_kind_has_its_own_name_and_its_wire_tag_is_its_place() {
    let mut names: Vec<&str> = MessageKind::ALL.iter().map(|k| k.name()).collect();
    assert!(!MessageKind::ALL.contains(&MessageKind::Handshake));
    for (tag, kind) in MessageKind::ALL.into_iter().enumerate() {
        assert_eq!(MessageKind::from_tag(tag as u8), Some(kind));
    }
    assert_eq!(MessageKind::from_tag(MessageKind::ALL.len() as u8), None);
    names.push(MessageKind::Handshake.name());
    let n = names.len();
    names.sort_unstable();
    names.dedup();
    assert_eq!(names.len(), n, "two kinds share a name");
}

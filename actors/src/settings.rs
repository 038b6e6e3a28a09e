//! One set of render settings, three spellings: the config's `[render]`
//! section, the wire's [`dray_protocol::RenderSettings`], and the kernel's
//! [`dray_trace::render::RenderSettings`]. The conversions live here; `dray
//! render` builds its kernel settings from its flags and shares the
//! reflection rule, and the cluster tests check that both give the same
//! pixels, bit for bit.

use dray_protocol as wire;
use dray_trace::render::{Isa, Packets, ReflectRule, RenderSettings};
use glam::Vec3;

/// The kernel's rule for a wire rule.
pub fn reflect_rule(r: &wire::Reflective) -> ReflectRule {
    match *r {
        wire::Reflective::All => ReflectRule::All,
        wire::Reflective::Ids { start, end } => ReflectRule::Ids(start..end),
        wire::Reflective::Color(c) => ReflectRule::Color(c),
    }
}

/// The kernel's settings for tiles of a scene of diagonal `scene_diagonal`
/// (the manifest's model bounds), traced with `isa` on `threads` threads.
pub fn kernel_settings(
    s: &wire::RenderSettings,
    scene_diagonal: f32,
    threads: usize,
    isa: Isa,
) -> RenderSettings {
    RenderSettings {
        shade: s.shade,
        shadows: s.shadows,
        light: Vec3::from_array(s.light_dir),
        threads,
        isa,
        scene_diagonal,
        reflections: u32::from(s.reflection_depth),
        reflective: reflect_rule(&s.reflective),
        reflectance: s.reflectance,
        voxel_colors: s.voxel_colors,
        // Each render thread picks per tile (`PacketChooser`).
        packets: Packets::Auto,
        occluder_cache: true,
    }
}

/// The wire settings of a config's `[render]` section.
pub fn wire_settings(r: &dray_config::RenderConfig) -> wire::RenderSettings {
    wire::RenderSettings {
        shade: true,
        shadows: r.shadows,
        reflection_depth: r.reflection_depth,
        light_dir: r.light_dir,
        reflective: r.reflective.clone(),
        reflectance: r.reflectance,
        voxel_colors: r.voxel_colors,
        want_depth: r.depth_and_ids,
        want_prim_ids: r.depth_and_ids,
    }
}

/// The wire camera of a config camera.
pub fn wire_camera(c: &dray_config::CameraConfig) -> wire::Camera {
    c.to_wire()
}

/// The kernel's camera for a wire camera and image size.
pub fn kernel_camera(c: &wire::Camera, width: u32, height: u32) -> dray_trace::camera::Camera {
    dray_trace::camera::Camera {
        eye: Vec3::from_array(c.eye),
        look: Vec3::from_array(c.look),
        up: Vec3::from_array(c.up),
        fov_degrees: c.fov_y_deg,
        width,
        height,
    }
}

//! The triangle record that flows from the importers through preprocessing.

use crate::geometry::Aabb;
use glam::Vec3;

/// Grey used for models that carry no colors.
pub const DEFAULT_COLOR: [u8; 4] = [200, 200, 200, 255];

/// One triangle, self-contained: what the importers produce and what a voxel
/// stores (after vertex de-duplication).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Triangle {
    /// Corner positions, in input order (the winding of the input face).
    pub positions: [Vec3; 3],
    /// Unit vertex normals for smooth shading (computed by the importer when
    /// the model has none).
    pub normals: [Vec3; 3],
    /// RGBA per corner; alpha is always 255 for now.
    pub colors: [[u8; 4]; 3],
    /// Index of the triangle in the ORIGINAL input (docs/design.md, "Conventions").
    pub id: u32,
}

impl Triangle {
    pub fn bounds(&self) -> Aabb {
        Aabb::from_points(&self.positions)
    }

    /// Unnormalized geometric normal (zero for a degenerate triangle).
    pub fn geometric_normal(&self) -> Vec3 {
        let [a, b, c] = self.positions;
        (b - a).cross(c - a)
    }

    pub fn centroid(&self) -> Vec3 {
        (self.positions[0] + self.positions[1] + self.positions[2]) / 3.0
    }
}

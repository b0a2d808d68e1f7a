//! Per-voxel ambient occlusion from the neighbourhood: for the face a ray
//! entered, the eight voxels around the empty cell in front of it darken
//! the face's corners (two sides or a side and a corner occlude a corner,
//! the classic voxel vertex rule), and the corners are interpolated
//! bilinearly at the hit point. Exact from the occupancy alone: no rays,
//! no noise, and the same on the CPU and in the GPU shader.

use glam::Vec3;

/// How much full occlusion darkens a face: the lighting is multiplied by
/// `1 − AO_STRENGTH · (1 − ao)`.
pub const AO_STRENGTH: f32 = 0.45;

/// Openness in `[0, 1]` (1: nothing around) of the face of local voxel
/// `cell` with outward `normal`, at hit point `p` (local frame), with
/// `solid` answering for local voxels. A zero normal (a ray that started
/// inside) is open.
///
/// ```
/// use brickworld::trace::face_ao;
/// use glam::Vec3;
/// // A floor voxel with a wall voxel beside the cell above it (+x side).
/// let solid = |c: [i32; 3]| c == [0, 0, 0] || c == [1, 1, 0];
/// let near_wall = face_ao(solid, [0, 0, 0], [0, 1, 0], Vec3::new(0.95, 1.0, 0.5));
/// let far_side = face_ao(solid, [0, 0, 0], [0, 1, 0], Vec3::new(0.05, 1.0, 0.5));
/// assert!(near_wall < 0.7 && far_side > 0.95);
/// ```
pub fn face_ao(solid: impl Fn([i32; 3]) -> bool, cell: [i32; 3], normal: [i32; 3], p: Vec3) -> f32 {
    let Some(a) = (0..3).find(|&a| normal[a] != 0) else {
        return 1.0;
    };
    let (u, v) = ((a + 1) % 3, (a + 2) % 3);
    let front: [i32; 3] = std::array::from_fn(|k| cell[k] + normal[k]);
    let at = |du: i32, dv: i32| {
        let mut c = front;
        c[u] += du;
        c[v] += dv;
        solid(c) as u32
    };
    let corner = |su: i32, sv: i32| {
        let (s1, s2, c) = (at(su, 0), at(0, sv), at(su, sv));
        if s1 + s2 == 2 {
            0.0
        } else {
            (3 - s1 - s2 - c) as f32 / 3.0
        }
    };
    let fu = (p.to_array()[u] - cell[u] as f32).clamp(0.0, 1.0);
    let fv = (p.to_array()[v] - cell[v] as f32).clamp(0.0, 1.0);
    let low = corner(-1, -1) + (corner(1, -1) - corner(-1, -1)) * fu;
    let high = corner(-1, 1) + (corner(1, 1) - corner(-1, 1)) * fu;
    low + (high - low) * fv
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn open_faces_are_one_and_corners_darken() {
        let none = |_: [i32; 3]| false;
        assert_eq!(
            face_ao(none, [3, 3, 3], [0, 1, 0], Vec3::new(3.5, 4.0, 3.5)),
            1.0
        );
        // Two walls meeting at the (-x, -z) corner of the cell above.
        let walls = |c: [i32; 3]| c[1] == 4 && (c[0] == 2 || c[2] == 2);
        let corner = face_ao(walls, [3, 3, 3], [0, 1, 0], Vec3::new(3.0, 4.0, 3.0));
        assert_eq!(corner, 0.0, "two sides occlude the corner fully");
        let centre = face_ao(walls, [3, 3, 3], [0, 1, 0], Vec3::new(3.5, 4.0, 3.5));
        assert!(centre > 0.0 && centre < 1.0);
        // A ray that started inside has no face.
        assert_eq!(face_ao(walls, [3, 3, 3], [0, 0, 0], Vec3::ZERO), 1.0);
    }
}

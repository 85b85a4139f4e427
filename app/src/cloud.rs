//! Built-in analytic clouds, so scenes and tests work before (and without) the
//! procedural modeler: a multi-lobe cumulus and a homogeneous sphere, both inside the
//! default cloud box [-0.5, 0.5]^3 (docs/conventions.md).

use engine::{Bounds3, DensityGrid};
use glam::{UVec3, Vec3};

/// The built-in clouds a scene can name with `grid.builtin`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Builtin {
    /// Ten overlapping lobes on a flattened base: strongly concave, homogeneous
    /// interior with a soft boundary; diameter about 0.9.
    Cumulus,
    /// A homogeneous sphere of radius 0.45 with a hard boundary (up to voxelization).
    Sphere,
}

impl Builtin {
    pub const NAMES: [&'static str; 2] = ["cumulus", "sphere"];

    pub fn from_name(name: &str) -> Option<Builtin> {
        match name {
            "cumulus" => Some(Builtin::Cumulus),
            "sphere" => Some(Builtin::Sphere),
            _ => None,
        }
    }

    pub fn density(&self, p: Vec3) -> f32 {
        match self {
            Builtin::Cumulus => cumulus_density(p),
            Builtin::Sphere => {
                if p.length() <= 0.45 {
                    1.0
                } else {
                    0.0
                }
            }
        }
    }

    /// Whether the density can be non-zero in box `b` (conservative): near a lobe,
    /// within the smooth union's reach (it lies at most k / 4 below the nearest lobe).
    pub fn may_be_nonzero(&self, b: Bounds3) -> bool {
        let near = |c: Vec3, r: f32| (c.clamp(b.min, b.max) - c).length() <= r;
        match self {
            Builtin::Cumulus => LOBES.iter().any(|&(x, y, z, r)| near(Vec3::new(x, y, z), r + 0.25 * 0.06 + 1e-4)),
            Builtin::Sphere => near(Vec3::ZERO, 0.45),
        }
    }

    /// The cloud voxelized at `resolution`^3 over [-0.5, 0.5]^3, in sparse bricks (as
    /// the modeler builds: the same values as dense, faster to render).
    pub fn grid(&self, resolution: u32) -> DensityGrid {
        let (dims, bounds) = (UVec3::splat(resolution), Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5)));
        DensityGrid::from_fn_sparse(dims, bounds, |b| self.may_be_nonzero(b), |p| self.density(p))
            .expect("built-in clouds are finite and non-negative")
    }
}

/// Lobes (centre, radius) of the built-in cumulus.
const LOBES: [(f32, f32, f32, f32); 10] = [
    (0.00, -0.10, 0.00, 0.28),
    (-0.22, -0.15, 0.05, 0.20),
    (0.24, -0.14, -0.04, 0.21),
    (0.05, 0.12, 0.02, 0.22),
    (-0.10, 0.20, -0.08, 0.15),
    (0.18, 0.08, 0.10, 0.16),
    (-0.30, -0.05, -0.10, 0.14),
    (0.32, -0.20, 0.12, 0.12),
    (0.00, -0.15, 0.25, 0.16),
    (0.05, -0.12, -0.24, 0.17),
];

/// Width of the density falloff inside the boundary (world units).
const FALLOFF: f32 = 0.04;

fn cumulus_density(p: Vec3) -> f32 {
    // Smooth union of the lobes' signed distances (polynomial smooth minimum).
    let mut d = f32::INFINITY;
    for &(x, y, z, r) in &LOBES {
        let di = (p - Vec3::new(x, y, z)).length() - r;
        d = smooth_min(d, di, 0.06);
    }
    // Flattened base.
    d = d.max(-(p.y + 0.3));
    smoothstep(0.0, FALLOFF, -d)
}

fn smooth_min(a: f32, b: f32, k: f32) -> f32 {
    if !a.is_finite() {
        return b;
    }
    let h = (0.5 + 0.5 * (b - a) / k).clamp(0.0, 1.0);
    b + (a - b) * h - k * h * (1.0 - h)
}

fn smoothstep(e0: f32, e1: f32, x: f32) -> f32 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cumulus_fits_the_box_and_is_dense_inside() {
        let g = Builtin::Cumulus.grid(32);
        assert_eq!(g.max_value(), 1.0);
        assert!(g.lookup(Vec3::new(0.0, -0.1, 0.0)) > 0.99);
        // Nothing touches the box faces.
        assert_eq!(g.max_on_boundary(), 0.0, "cloud touches the box");
    }

    /// The brick test never rejects density: every non-zero voxel of a dense build
    /// lies in an accepted brick, and the sparse build equals the dense one.
    #[test]
    fn brick_test_is_conservative() {
        for b in [Builtin::Cumulus, Builtin::Sphere] {
            let res = 72u32;
            let dense =
                DensityGrid::from_fn(UVec3::splat(res), Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5)), |p| {
                    b.density(p)
                })
                .unwrap();
            assert!(b.grid(res).to_dense_vec() == dense.to_dense_vec(), "{b:?}: the built grid differs");
            let sparse = DensityGrid::from_fn_sparse(
                UVec3::splat(res),
                Bounds3::new(Vec3::splat(-0.5), Vec3::splat(0.5)),
                |bx| b.may_be_nonzero(bx),
                |p| b.density(p),
            )
            .unwrap();
            assert_eq!(sparse.to_dense_vec(), dense.to_dense_vec(), "{b:?}");
            let vs = 1.0 / res as f32;
            let bd = dense.brick_dims();
            let accepted = (0..bd.x * bd.y * bd.z)
                .filter(|i| {
                    let c = UVec3::new(i % bd.x, (i / bd.x) % bd.y, i / (bd.x * bd.y)) * engine::grid::BRICK;
                    let lo = Vec3::splat(-0.5) + c.as_vec3() * vs;
                    b.may_be_nonzero(Bounds3::new(lo, lo + engine::grid::BRICK as f32 * vs))
                })
                .count();
            assert!(accepted < (bd.x * bd.y * bd.z) as usize, "{b:?}: the brick test rejects nothing");
        }
    }
}

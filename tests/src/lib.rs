//! Shared fixtures for the cross-crate tests.

use engine::{Bounds3, Camera, DensityGrid, Medium, PhaseFunction, Scene, Sky, Sun};
use glam::{UVec3, Vec3};
use std::sync::Arc;

/// A slab of constant density 1 between y = -h/2 and y = h/2 (`ny` voxels thick),
/// wide enough (4 x 4 world units) that oblique test rays never see its sides.
pub fn slab_grid(ny: u32, thickness: f32) -> DensityGrid {
    let (nx, nz) = (64, 64);
    DensityGrid::from_bounds(
        UVec3::new(nx, ny, nz),
        vec![1.0; (nx * ny * nz) as usize],
        Bounds3::new(Vec3::new(-2.0, -0.5 * thickness, -2.0), Vec3::new(2.0, 0.5 * thickness, 2.0)),
    )
    .unwrap()
}

/// Density rising linearly with y: d(y) = a + b y at every voxel centre.
pub fn ramp_grid(ny: u32, a: f32, b: f32) -> DensityGrid {
    let bounds = Bounds3::new(Vec3::new(-2.0, -0.5, -2.0), Vec3::new(2.0, 0.5, 2.0));
    DensityGrid::from_fn(UVec3::new(32, ny, 32), bounds, |p| a + b * p.y).unwrap()
}

/// A homogeneous voxelized sphere of radius 0.45 in the unit box.
pub fn sphere_grid(n: u32) -> DensityGrid {
    app::cloud::Builtin::Sphere.grid(n)
}

/// A small scene around the built-in cumulus, camera looking along -z.
pub fn cumulus_scene(
    res: u32,
    rho: f32,
    albedo: f32,
    phase: PhaseFunction,
    sun: Option<Sun>,
    sky: Vec3,
    size: u32,
) -> Scene {
    let grid = Arc::new(app::cloud::Builtin::Cumulus.grid(res));
    Scene {
        medium: Medium::new(grid, rho, albedo, phase).unwrap(),
        sun,
        sky: Sky::uniform(sky),
        camera: Camera::new(Vec3::new(0.0, 0.0, 2.6), Vec3::ZERO, Vec3::Y, 30.0, size, size).unwrap(),
    }
}

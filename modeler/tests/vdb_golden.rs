//! Our VDB writer against a file written by libopenvdb 10.0.1 itself
//! (tests/data/openvdb_tiny_mask.vdb: voxels (0,0,0) = 1, (1,2,3) = 0.5, (7,7,7) = 0.25,
//! voxel size 0.5, translation (1, 2, 3), compression "active mask"; made with
//! `io::File::setCompression(COMPRESS_ACTIVE_MASK)`). Header, UUID and the grid
//! metadata block legitimately differ; the transform and the whole tree must match
//! byte for byte.

use engine::DensityGrid;
use glam::{UVec3, Vec3};

fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    hay.windows(needle.len()).position(|w| w == needle)
}

#[test]
fn tree_and_transform_match_libopenvdb() {
    let reference = std::fs::read(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/openvdb_tiny_mask.vdb")).unwrap();
    let mut data = vec![0.0f32; 512];
    let idx = |x: usize, y: usize, z: usize| x + 8 * (y + 8 * z);
    data[idx(0, 0, 0)] = 1.0;
    data[idx(1, 2, 3)] = 0.5;
    data[idx(7, 7, 7)] = 0.25;
    // OpenVDB voxel (i, j, k) sits at translation + 0.5 (i, j, k): our origin is half a
    // voxel before the first centre.
    let grid = DensityGrid::new(UVec3::splat(8), data, Vec3::new(1.0, 2.0, 3.0) - 0.25, Vec3::splat(0.5)).unwrap();
    let ours = modeler::vdb::vdb_bytes(&grid, "density").unwrap();
    let map = b"UniformScaleTranslateMap";
    let (a, b) = (find(&reference, map).unwrap(), find(&ours, map).unwrap());
    assert_eq!(reference.len() - a, ours.len() - b, "transform + tree sizes differ");
    assert!(reference[a..] == ours[b..], "transform + tree bytes differ");
    // Same header up to the UUID, same descriptor after it.
    assert_eq!(&reference[..0x15], &ours[..0x15]);
    // Grid descriptor offsets are consistent: end pos = file length.
    let end = i64::from_le_bytes(ours[0x74..0x7c].try_into().unwrap());
    assert_eq!(end as usize, ours.len());
}

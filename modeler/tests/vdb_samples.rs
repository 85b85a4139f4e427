//! The VDB importer against files written by OpenVDB itself (tests/data/vdb, made by
//! its make_fixtures.py, each with a JSON of its true contents computed by OpenVDB),
//! the round trip through our writer, and bad input.

use modeler::vdb::{VdbReadError, read_vdb, read_vdb_bytes, vdb_bytes};
use serde_json::Value;
use std::path::PathBuf;

fn samples_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/data/vdb")
}

fn truth(name: &str) -> Value {
    serde_json::from_str(&std::fs::read_to_string(samples_dir().join(format!("{name}.json"))).unwrap()).unwrap()
}

fn ivec(v: &Value) -> [i32; 3] {
    [v[0].as_i64().unwrap() as i32, v[1].as_i64().unwrap() as i32, v[2].as_i64().unwrap() as i32]
}

fn check_grid(file: &str, grid_name: &str, requested: Option<&str>) {
    let t = truth(file);
    let g = t["grids"].as_array().unwrap().iter().find(|g| g["name"] == grid_name).unwrap();
    let imp = read_vdb(&samples_dir().join(format!("{file}.vdb")), requested).unwrap_or_else(|e| panic!("{file}: {e}"));
    assert_eq!(imp.name, grid_name);
    // Grids listed in file order.
    let names: Vec<&str> = t["grid_names"].as_array().unwrap().iter().map(|v| v.as_str().unwrap()).collect();
    assert_eq!(imp.grids.iter().map(|(n, _)| n.as_str()).collect::<Vec<_>>(), names, "{file}");
    assert_eq!(imp.active_voxels, g["active_voxel_count"].as_u64().unwrap(), "{file}: active voxels");
    assert_eq!(imp.active_tiles, g["active_tile_count"].as_u64().unwrap(), "{file}: active tiles");
    let sum = g["sum_active"].as_f64().unwrap();
    assert!((imp.sum - sum).abs() <= 1e-5 * sum.abs(), "{file}: sum {} vs {sum}", imp.sum);
    let bbox = &g["index_bbox_active"];
    let hi = imp.index_min + imp.grid.dims().as_ivec3() - 1;
    assert_eq!(imp.index_min.to_array(), ivec(&bbox[0]), "{file}: bbox min");
    assert_eq!(hi.to_array(), ivec(&bbox[1]), "{file}: bbox max");
    // Transform: index_to_world rows.
    let m = &g["transform"]["index_to_world"];
    for a in 0..3 {
        let s = m[a][a].as_f64().unwrap();
        let tr = m[a][3].as_f64().unwrap();
        assert!((imp.voxel_size[a] - s).abs() <= 1e-6 * s.abs(), "{file}: scale {a}");
        assert!((imp.translation[a] - tr).abs() <= 1e-6 * s.abs().max(1.0), "{file}: translation {a}");
    }
    // Probe values, through the dense grid and through a world-space lookup at the
    // voxel centre (which checks the placement and cell centring).
    for probe in g["values_at"].as_array().unwrap() {
        let ijk = glam::IVec3::from_array(ivec(&probe["ijk"]));
        let want = probe["value"].as_f64().unwrap() as f32;
        let r = ijk - imp.index_min;
        let dims = imp.grid.dims().as_ivec3();
        let got = if r.cmpge(glam::IVec3::ZERO).all() && r.cmplt(dims).all() {
            imp.grid.voxel(r.x as u32, r.y as u32, r.z as u32)
        } else {
            0.0
        };
        assert!((got - want).abs() <= 1e-6, "{file}: value at {ijk}: {got} vs {want}");
        let world = (imp.translation + imp.voxel_size * ijk.as_dvec3()).as_vec3();
        let looked_up = imp.grid.lookup(world);
        assert!(
            (looked_up - want).abs() <= 1e-5 * imp.grid.max_value().max(1.0),
            "{file}: lookup at {world} ({ijk}): {looked_up} vs {want}"
        );
    }
}

#[test]
fn sphere_dense() {
    check_grid("sphere_dense", "density", None);
}

#[test]
fn cloud_sparse_with_tiles() {
    check_grid("cloud_sparse", "density", None);
}

#[test]
fn transformed_zip() {
    check_grid("transformed_zip", "density", None);
}

#[test]
fn multi_grid_by_default_and_by_name() {
    check_grid("multi_grid", "density", None);
    check_grid("multi_grid", "temperature", Some("temperature"));
    let e = read_vdb(&samples_dir().join("multi_grid.vdb"), Some("velocity")).unwrap_err();
    assert!(matches!(e, VdbReadError::NoSuchGrid { .. }));
    let msg = e.to_string();
    assert!(msg.contains("velocity") && msg.contains("'temperature'") && msg.contains("'density'"), "{msg}");
}

#[test]
fn half_float_is_refused_clearly() {
    let e = read_vdb(&samples_dir().join("half_float.vdb"), None).unwrap_err();
    let msg = e.to_string();
    assert!(matches!(e, VdbReadError::Unsupported { .. }), "{msg}");
    assert!(msg.contains("half_float.vdb") && msg.contains("half floats") && msg.contains("blosc"), "{msg}");
}

#[test]
fn round_trip_through_our_writer() {
    let params = modeler::preset("scene-c").unwrap();
    let grid = modeler::build_grid(&params, 40).unwrap();
    let bytes = vdb_bytes(&grid, "density").unwrap();
    let imp = read_vdb_bytes(&bytes, "mem.vdb", None).unwrap();
    // The importer crops to the active bounding box; compare voxel by voxel.
    let n = grid.dims();
    let (lo, d) = (imp.index_min.as_uvec3(), imp.grid.dims());
    let mut count = 0u64;
    for z in 0..n.z {
        for y in 0..n.y {
            for x in 0..n.x {
                let v = grid.voxel(x, y, z);
                let inside = x >= lo.x && y >= lo.y && z >= lo.z && x < lo.x + d.x && y < lo.y + d.y && z < lo.z + d.z;
                let w = if inside { imp.grid.voxel(x - lo.x, y - lo.y, z - lo.z) } else { 0.0 };
                assert_eq!(v, w, "voxel ({x}, {y}, {z})");
                count += (v != 0.0) as u64;
            }
        }
    }
    assert_eq!(imp.active_voxels, count);
    // Same world placement: a voxel centre maps to the same world point.
    let c = grid.origin() + (lo.as_vec3() + 0.5) * grid.voxel_size();
    assert!((imp.grid.origin() + 0.5 * imp.grid.voxel_size() - c).length() < 1e-5);
}

/// Truncated and damaged files are refused with an error; nothing panics.
#[test]
fn bad_files_give_errors_not_crashes() {
    let e = read_vdb_bytes(b"this is a text file, not a volume", "notes.txt", None).unwrap_err();
    assert_eq!(e.to_string(), "notes.txt: not an OpenVDB file (bad magic number)");
    assert!(matches!(read_vdb_bytes(&[], "empty.vdb", None), Err(VdbReadError::NotVdb { .. })));
    let e = read_vdb(&samples_dir().join("does-not-exist.vdb"), None).unwrap_err();
    assert!(e.to_string().contains("does-not-exist.vdb"));
    for file in ["sphere_dense", "cloud_sparse", "transformed_zip", "multi_grid", "half_float"] {
        let data = std::fs::read(samples_dir().join(format!("{file}.vdb"))).unwrap();
        // Truncations at 40 points through the file.
        for i in 1..40 {
            let cut = data.len() * i / 40;
            let r = read_vdb_bytes(&data[..cut], file, None);
            assert!(r.is_err(), "{file} cut at {cut} bytes was accepted");
        }
        // A wrong version number.
        let mut v = data.clone();
        v[8..12].copy_from_slice(&200u32.to_le_bytes());
        let msg = read_vdb_bytes(&v, file, None).unwrap_err().to_string();
        assert!(msg.contains("version 200"), "{msg}");
        // Damaged bytes in the header, descriptors and grid metadata (where the
        // preflight answers for the whole importer).
        let mut rng = engine::Rng::new(99, file.len() as u64, 0);
        for _ in 0..200 {
            let mut d = data.clone();
            let at = (rng.uniform() * 400.0) as usize % d.len();
            d[at] ^= 1 << (rng.next_u32() % 8);
            let _ = read_vdb_bytes(&d, file, None); // Ok or Err, never a panic
        }
    }
}

/// Found by `cargo fuzz run vdb_import`: a damaged zip/blosc chunk size of 64 GiB
/// made vdb-rs allocate it and abort the process (the tree scan refuses it first); a
/// metadata entry whose stored size disagreed with its type made vdb-rs lose its
/// place and allocate a 4 GiB string (the preflight checks fixed-size types).
#[test]
fn fuzz_regressions() {
    for name in ["fuzz_huge_chunk.vdb", "fuzz_metadata_size.vdb"] {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data").join(name);
        let e = read_vdb_bytes(&std::fs::read(path).unwrap(), name, None).unwrap_err();
        assert!(matches!(e, VdbReadError::Corrupt { .. }), "{name}: {e}");
    }
}

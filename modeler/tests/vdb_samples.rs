//! The VDB importer against files written by OpenVDB itself (tests/data/vdb, made by
//! its make_fixtures.py, each with a JSON of its true contents computed by OpenVDB),
//! float32 grids against vdb-rs 0.6, the round trip through our writer, and bad input.

use glam::{DVec3, IVec3, UVec3};
use modeler::vdb::{VdbImport, VdbReadError, read_vdb, read_vdb_bytes, vdb_bytes};
use rayon::prelude::*;
use serde_json::Value;
use std::path::PathBuf;

const FIXTURES: [&str; 8] = [
    "sphere_dense",
    "cloud_sparse",
    "transformed_zip",
    "multi_grid",
    "half_float",
    "half_zip",
    "half_sparse",
    "sparse_far",
];

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
    assert_eq!(imp.active_min.to_array(), ivec(&bbox[0]), "{file}: bbox min");
    assert_eq!(imp.active_max.to_array(), ivec(&bbox[1]), "{file}: bbox max");
    // A dense import's box is the active box; a sparse one's contains it in whole leaves.
    let hi = imp.index_min + imp.grid.dims().as_ivec3() - 1;
    if imp.grid.is_sparse() {
        assert!(imp.index_min.cmple(imp.active_min).all() && hi.cmpge(imp.active_max).all(), "{file}: box");
        assert!(imp.index_min.rem_euclid(IVec3::splat(8)) == IVec3::ZERO, "{file}: box not leaf-aligned");
    } else {
        assert_eq!((imp.index_min, hi), (imp.active_min, imp.active_max), "{file}: box");
    }
    // Transform: index_to_world rows.
    let m = &g["transform"]["index_to_world"];
    for a in 0..3 {
        let s = m[a][a].as_f64().unwrap();
        let tr = m[a][3].as_f64().unwrap();
        assert!((imp.voxel_size[a] - s).abs() <= 1e-6 * s.abs(), "{file}: scale {a}");
        assert!((imp.translation[a] - tr).abs() <= 1e-6 * s.abs().max(1.0), "{file}: translation {a}");
    }
    // Probe values, through the dense grid and through a world-space lookup at the
    // voxel centre (which checks the placement and cell centring). OpenVDB's values
    // are f32 (half floats converted to f32) written as f64, so they compare exactly;
    // inactive voxels import as 0 whatever value they hold.
    for probe in g["values_at"].as_array().unwrap() {
        let ijk = IVec3::from_array(ivec(&probe["ijk"]));
        let want = if probe["active"].as_bool().unwrap() { probe["value"].as_f64().unwrap() as f32 } else { 0.0 };
        let r = ijk - imp.index_min;
        let dims = imp.grid.dims().as_ivec3();
        let got = if r.cmpge(IVec3::ZERO).all() && r.cmplt(dims).all() {
            imp.grid.voxel(r.x as u32, r.y as u32, r.z as u32)
        } else {
            0.0
        };
        assert_eq!(got.to_bits(), want.to_bits(), "{file}: value at {ijk}: {got} vs {want}");
        let world = (imp.translation + imp.voxel_size * ijk.as_dvec3()).as_vec3();
        let looked_up = imp.grid.lookup(world);
        // The lookup works in f32: the voxel centre lands a few ulps of the world
        // position off, which at an isolated voxel (all neighbours 0) shows in full.
        let ulps = 4.0 * f32::EPSILON * (world.abs() + imp.grid.origin().abs()).max_element();
        let tolerance = imp.grid.max_value().max(1.0) * (1e-5 + ulps / imp.grid.voxel_size().min_element());
        assert!(
            (looked_up - want).abs() <= tolerance,
            "{file}: lookup at {world} ({ijk}): {looked_up} vs {want} (tolerance {tolerance})"
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
fn half_float_blosc() {
    check_grid("half_float", "density", None);
}

#[test]
fn half_float_zip_imports_as_the_blosc_file() {
    check_grid("half_zip", "density", None);
    let (a, b) = (
        read_vdb(&samples_dir().join("half_float.vdb"), None).unwrap(),
        read_vdb(&samples_dir().join("half_zip.vdb"), None).unwrap(),
    );
    assert_same(&a, &b, "half_zip vs half_float");
}

/// A 128^3 tile, 8^3 tiles, partial leaves, isolated voxels far apart, and inactive
/// values other than the background (stored as 32-bit floats in half-float arrays).
#[test]
fn half_float_sparse_with_tiles() {
    check_grid("half_sparse", "density", None);
    let imp = read_vdb(&samples_dir().join("half_sparse.vdb"), None).unwrap();
    assert_eq!(imp.grid.dims(), UVec3::new(232, 170, 198));
    // Every voxel of the 128^3 tile [0, 127]^3 holds its value.
    let r = (IVec3::ZERO - imp.index_min).as_uvec3();
    for (x, y, z) in [(0, 0, 0), (127, 0, 0), (0, 127, 0), (0, 0, 127), (127, 127, 127), (31, 77, 120)] {
        assert_eq!(imp.grid.voxel(r.x + x, r.y + y, r.z + z), 0.375);
    }
}

/// Voxels thousands of voxels apart with tiles: an active box of 5.2e9 voxels (19 GiB
/// as dense f32) imports sparsely in a few MiB, the 128^3 tile as shared constant
/// bricks, and a medium over it traces the tile's exact optical depth.
#[test]
fn far_apart_voxels_import_sparsely() {
    check_grid("sparse_far", "density", None);
    let imp = read_vdb(&samples_dir().join("sparse_far.vdb"), None).unwrap();
    assert!(imp.grid.is_sparse());
    let d = imp.grid.dims();
    let dense_bytes = 4 * d.x as u64 * d.y as u64 * d.z as u64;
    assert!(dense_bytes > 16 << 30, "{d}");
    assert!(imp.grid.memory_bytes() < 64 << 20, "{} bytes", imp.grid.memory_bytes());
    let r = (IVec3::new(128, 0, 0) - imp.index_min).as_uvec3();
    for (x, y, z) in [(0, 0, 0), (127, 0, 0), (0, 127, 0), (0, 0, 127), (127, 127, 127), (31, 77, 120)] {
        assert_eq!(imp.grid.voxel(r.x + x, r.y + y, r.z + z), 0.5);
    }
    // Along x through the tile's middle: density 0.5 over 128 voxels of 0.001, the
    // half-voxel tapers at both faces included (mass-preserving interpolation).
    let rho = 10.0f32;
    let medium =
        engine::Medium::new(std::sync::Arc::new(imp.grid.clone()), rho, 1.0, engine::PhaseFunction::Isotropic).unwrap();
    let (o, dir) = (glam::Vec3::new(0.1, 0.064, 0.064), glam::Vec3::X);
    let tau = medium.optical_depth(o, dir, 0.2, 1e-5, f32::INFINITY) as f64;
    let want = rho as f64 * 0.5 * 128.0 * 0.001;
    assert!((tau - want).abs() < 1e-3 * want, "optical depth {tau} vs {want}");
}

fn assert_same(a: &VdbImport, b: &VdbImport, what: &str) {
    assert_eq!(a.grid.dims(), b.grid.dims(), "{what}: dims");
    assert_eq!(a.index_min, b.index_min, "{what}: index box");
    assert!(
        a.grid.to_dense_vec().iter().zip(&b.grid.to_dense_vec()).all(|(x, y)| x.to_bits() == y.to_bits()),
        "{what}: values"
    );
    assert_eq!(a.grid.origin().to_array().map(f32::to_bits), b.grid.origin().to_array().map(f32::to_bits), "{what}");
    assert_eq!(a.grid.voxel_size().to_array().map(f32::to_bits), b.grid.voxel_size().to_array().map(f32::to_bits));
    assert_eq!((a.active_voxels, a.active_tiles, a.sum.to_bits()), (b.active_voxels, b.active_tiles, b.sum.to_bits()));
    assert_eq!((a.voxel_size, a.translation), (b.voxel_size, b.translation), "{what}: transform");
}

/// A float32 grid imported through vdb-rs 0.6 (which reads 32-bit grids correctly
/// while their index coordinates stay within +-2^24, the range of its f32 positions)
/// and resampled into a dense grid over the active box: the values, box, transform
/// and sum (accumulated in vdb-rs's iteration order) the importer must reproduce.
struct Reference {
    values: Vec<f32>,
    lo: IVec3,
    dims: UVec3,
    origin: glam::Vec3,
    active: u64,
    tiles: u64,
    sum: f64,
    scale: DVec3,
    translation: DVec3,
}

fn vdb_rs_reference(data: &[u8], name: &str) -> Reference {
    let mut r = vdb_rs::VdbReader::new(std::io::Cursor::new(data)).unwrap();
    let g = r.read_grid::<f32>(name).unwrap();
    let (scale, translation) = match &g.transform {
        vdb_rs::Map::UniformScaleMap { scale_values: s, .. } => (DVec3::new(s.x, s.y, s.z), DVec3::ZERO),
        vdb_rs::Map::ScaleTranslateMap { scale_values: s, translation: t, .. } => {
            (DVec3::new(s.x, s.y, s.z), DVec3::new(t.x, t.y, t.z))
        }
    };
    let items: Vec<(IVec3, i32, f32)> = g
        .iter()
        .map(|(pos, v, level)| (IVec3::new(pos.x as i32, pos.y as i32, pos.z as i32), level.scale() as i32, v))
        .collect();
    let (mut lo, mut hi) = (IVec3::MAX, IVec3::MIN);
    let (mut active, mut tiles, mut sum) = (0u64, 0u64, 0.0f64);
    for &(c, edge, v) in &items {
        lo = lo.min(c);
        hi = hi.max(c + edge - 1);
        let n = (edge as u64).pow(3);
        active += n;
        tiles += (edge > 1) as u64;
        sum += v as f64 * n as f64;
    }
    let dims = (hi - lo + 1).as_uvec3();
    let mut values = vec![0.0f32; dims.x as usize * dims.y as usize * dims.z as usize];
    for &(c, edge, v) in &items {
        for z in 0..edge {
            for y in 0..edge {
                for x in 0..edge {
                    let r = (c + IVec3::new(x, y, z) - lo).as_uvec3();
                    values[r.x as usize + dims.x as usize * (r.y as usize + dims.y as usize * r.z as usize)] = v;
                }
            }
        }
    }
    let origin = (translation + scale * (lo.as_dvec3() - 0.5)).as_vec3();
    Reference { values, lo, dims, origin, active, tiles, sum, scale, translation }
}

/// Float32 grids import bit for bit as through vdb-rs 0.6: OpenVDB's files (blosc,
/// zip, tiles, two grids), libopenvdb's tiny reference file, and our writer's.
#[test]
fn float_grids_match_vdb_rs() {
    let mut files: Vec<(String, Vec<u8>, &str)> = Vec::new();
    for file in ["sphere_dense", "cloud_sparse", "transformed_zip", "multi_grid"] {
        files.push((file.into(), std::fs::read(samples_dir().join(format!("{file}.vdb"))).unwrap(), "density"));
    }
    let multi = std::fs::read(samples_dir().join("multi_grid.vdb")).unwrap();
    files.push(("multi_grid/temperature".into(), multi, "temperature"));
    let tiny = std::fs::read(samples_dir().join("../openvdb_tiny_mask.vdb")).unwrap();
    files.push(("openvdb_tiny_mask".into(), tiny, "density"));
    for preset in ["scene-a", "scene-c"] {
        let grid = modeler::build_grid(&modeler::preset(preset).unwrap(), 48).unwrap();
        files.push((preset.into(), vdb_bytes(&grid, "density").unwrap(), "density"));
    }
    for (what, data, grid) in &files {
        let want = vdb_rs_reference(data, grid);
        let got = read_vdb_bytes(data, what, Some(grid)).unwrap();
        assert_eq!((got.index_min, got.grid.dims()), (want.lo, want.dims), "{what}: box");
        assert!(
            got.grid.to_dense_vec().iter().zip(&want.values).all(|(a, b)| a.to_bits() == b.to_bits()),
            "{what}: values"
        );
        assert_eq!(got.grid.origin().to_array().map(f32::to_bits), want.origin.to_array().map(f32::to_bits), "{what}");
        assert_eq!(got.grid.voxel_size(), want.scale.as_vec3(), "{what}");
        assert_eq!((got.voxel_size, got.translation), (want.scale, want.translation), "{what}: transform");
        assert_eq!((got.active_voxels, got.active_tiles), (want.active, want.tiles), "{what}: counts");
        assert_eq!(got.sum.to_bits(), want.sum.to_bits(), "{what}: sum {} vs {}", got.sum, want.sum);
    }
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
    for file in FIXTURES {
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
        // preflight answers for the whole importer), then anywhere: in the tree's
        // masks, chunk sizes and compressed values. What imports must be finite (a
        // flipped bit in a blosc chunk, which has no checksum, can give other values).
        let mut rng = engine::Rng::new(99, file.len() as u64, 0);
        let mut flips: Vec<(usize, u8)> =
            (0..200).map(|_| ((rng.uniform() * 400.0) as usize % data.len(), 1 << (rng.next_u32() % 8))).collect();
        flips.extend(
            (0..200).map(|_| ((rng.uniform() * data.len() as f32) as usize % data.len(), 1 << (rng.next_u32() % 8))),
        );
        flips.par_iter().for_each(|&(at, bit)| {
            let mut d = data.clone();
            d[at] ^= bit;
            if let Ok(imp) = read_vdb_bytes(&d, file, None) {
                assert!(imp.grid.max_value().is_finite() && imp.sum.is_finite(), "{file}: byte {at}");
            }
        });
    }
}

/// Files found by `cargo fuzz run vdb_import`: a damaged chunk size of 64 GiB, and a
/// metadata entry whose stored size disagrees with its type. The preflight refuses
/// both before anything is allocated from them.
#[test]
fn fuzz_regressions() {
    for name in ["fuzz_huge_chunk.vdb", "fuzz_metadata_size.vdb"] {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data").join(name);
        let e = read_vdb_bytes(&std::fs::read(path).unwrap(), name, None).unwrap_err();
        assert!(matches!(e, VdbReadError::Corrupt { .. }), "{name}: {e}");
    }
}

/// Messages for grids that cannot be read say what the file holds: a vector grid
/// named "density" is named as such (not "no grid named 'density'"), and a damaged
/// transform name is shown escaped, not as raw control characters.
#[test]
fn messages_say_what_the_file_holds() {
    let grid =
        engine::DensityGrid::from_fn(UVec3::splat(4), engine::Bounds3::new(glam::Vec3::ZERO, glam::Vec3::ONE), |p| p.x)
            .unwrap();
    let bytes = vdb_bytes(&grid, "density").unwrap();
    let replace = |from: &[u8], to: &[u8]| -> Vec<u8> {
        assert_eq!(from.len(), to.len());
        let at = bytes.windows(from.len()).position(|w| w == from).expect("the string is in the file");
        let mut b = bytes.clone();
        b[at..at + to.len()].copy_from_slice(to);
        b
    };
    let vec3 = replace(b"Tree_float_5_4_3", b"Tree_vec3s_5_4_3");
    let e = read_vdb_bytes(&vec3, "velocity.vdb", None).unwrap_err().to_string();
    assert!(e.contains("'density' holds Tree_vec3s_5_4_3") && e.contains("float grids"), "{e}");
    assert!(!e.contains("no grid named"), "{e}");
    let bell = replace(b"UniformScaleTranslateMap", b"Uniform\x07\x1b[2JTranslateMap");
    let e = read_vdb_bytes(&bell, "bell.vdb", None).unwrap_err().to_string();
    assert!(!e.chars().any(|c| c.is_control()), "raw control characters in {e:?}");
    assert!(e.contains("\\u{7}"), "{e}");
}

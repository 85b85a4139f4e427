//! `nimbus bench model`: cloud rebuild times per preset and resolution, and the time
//! to import a 256^3 VDB.

use crate::cli::common::init_threads;
use crate::output;
use anyhow::Result;
use clap::Args;
use std::time::Instant;

#[derive(Args, Debug)]
pub struct BenchModelArgs {
    /// Repetitions per measurement (the median is reported).
    #[arg(long, default_value_t = 5)]
    pub reps: u32,
    #[arg(long)]
    pub threads: Option<usize>,
}

/// Median build and import times.
pub fn bench_model(args: BenchModelArgs) -> Result<()> {
    let threads = init_threads(args.threads)?;
    println!("bench model: median of {} builds, {threads} threads", args.reps);
    let mut results = Vec::new();
    for name in ["scene-a", "scene-b", "scene-c"] {
        let params = modeler::preset(name).expect("preset");
        for res in [64u32, 128, 256] {
            let mut times: Vec<f64> = (0..args.reps.max(1))
                .map(|_| {
                    let t = Instant::now();
                    let g = modeler::build_grid(&params, res).expect("valid preset");
                    std::hint::black_box(g.max_value());
                    t.elapsed().as_secs_f64()
                })
                .collect();
            times.sort_by(f64::total_cmp);
            let median = times[times.len() / 2];
            println!("  {name} {res:>3}^3: {:>8.1} ms", median * 1e3);
            results.push(serde_json::json!({"preset": name, "resolution": res, "median_seconds": median}));
        }
    }
    // Importing a 256^3 VDB (written by us from scene-a, active-mask compression).
    let grid = modeler::build_grid(&modeler::preset("scene-a").expect("preset"), 256)?;
    let dir = tempfile::tempdir()?;
    let path = dir.path().join("scene-a.vdb");
    output::write_bytes_atomically(&path, &modeler::vdb::vdb_bytes(&grid, "density")?)?;
    let mut times: Vec<f64> = (0..args.reps.max(1))
        .map(|_| {
            let t = Instant::now();
            let imp = modeler::vdb::read_vdb(&path, None).expect("our own file");
            std::hint::black_box(imp.active_voxels);
            t.elapsed().as_secs_f64()
        })
        .collect();
    times.sort_by(f64::total_cmp);
    let median = times[times.len() / 2];
    println!("  import 256^3 VDB (scene-a): {:>8.1} ms", median * 1e3);
    results.push(serde_json::json!({"import_vdb_256": median}));
    println!("{}", serde_json::json!({"bench": "model", "threads": threads, "results": results}));
    Ok(())
}

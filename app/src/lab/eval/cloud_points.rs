//! `nimbus eval cloud-points`: a cloud-aware model's relative bias on point data sets
//! (`nimbus datagen cloud`), overall, per scattering vertex of the camera path and per
//! cloud, and point by point (the RMS error an image of the points would show, the
//! targets' noise removed). With `datagen cloud --sun ... --view-sun-cos ...` the points reproduce one
//! lighting of `nimbus eval`, in seconds instead of an image study.

use anyhow::Result;
use clap::Args;
use models::cloud::CloudModel;
use models::cloud::datagen::CloudDataset;
use models::cloud::train::{BiasReport, ensemble_bias_report};
use std::path::PathBuf;
use std::sync::Arc;

#[derive(Args, Debug)]
pub struct EvalCloudPointsArgs {
    /// Data sets from `nimbus datagen cloud` (training or held-out).
    #[arg(required = true)]
    pub data: Vec<PathBuf>,
    /// Model files, comma separated (default: the shipped cloud-aware model).
    #[arg(long, value_delimiter = ',')]
    pub model: Vec<PathBuf>,
    /// Also report the mean of the models' predictions as one more row ("ensemble"):
    /// the target a student distilled from them is fitted to.
    #[arg(long)]
    pub ensemble: bool,
}

/// One row of the table: a data set, a model, the bias over all points and per vertex.
#[derive(Debug)]
pub struct PointsRow {
    pub data: String,
    pub model: String,
    pub all: BiasReport,
    /// Vertex 1, 2, 3 (None where the set has no such points).
    pub by_vertex: [Option<BiasReport>; 3],
}

pub fn eval_cloud_points(args: &EvalCloudPointsArgs) -> Result<Vec<PointsRow>> {
    let loaded: Vec<(String, Arc<CloudModel>)> = if args.model.is_empty() {
        vec![("shipped".into(), CloudModel::shipped()?)]
    } else {
        args.model
            .iter()
            .map(|p| Ok((p.display().to_string(), Arc::new(CloudModel::load(p)?))))
            .collect::<Result<_>>()?
    };
    // Each model alone, then (with --ensemble) all of them averaged.
    let mut models: Vec<(String, Vec<Arc<CloudModel>>)> =
        loaded.iter().map(|(name, m)| (name.clone(), vec![m.clone()])).collect();
    if args.ensemble {
        models.push((format!("ensemble of {}", loaded.len()), loaded.iter().map(|(_, m)| m.clone()).collect()));
    }
    println!(
        "| data | model | points | bias (se) | vertex 1 | vertex 2 | vertex 3 | per-cloud median, p90 | point RMS error |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    let mut rows = vec![];
    for dir in &args.data {
        let ds = CloudDataset::load(dir)?;
        let clouds: Vec<(u32, u64)> = (0..ds.len()).map(|i| (0, ds.cloud_of(i))).collect();
        let all_rows: Vec<usize> = (0..ds.len()).collect();
        for (name, model) in &models {
            let members: Vec<&CloudModel> = model.iter().map(|m| m.as_ref()).collect();
            let report = |rows: &[usize]| ensemble_bias_report(&members, &ds.features, &ds.targets, &clouds, rows);
            let by_vertex = [1.0f32, 2.0, 3.0].map(|v| {
                let rows: Vec<usize> = all_rows.iter().copied().filter(|&i| ds.targets[i * 5 + 4] == v).collect();
                (!rows.is_empty()).then(|| report(&rows))
            });
            let all = report(&all_rows);
            let pct = |r: &Option<BiasReport>| r.as_ref().map_or("-".into(), |r| format!("{:+.2} %", 100.0 * r.bias));
            println!(
                "| {} | {name} | {} | {:+.2} % ({:.2} %) | {} | {} | {} | {:.1} %, {:.1} % | {:.1} % |",
                dir.display(),
                all.points,
                100.0 * all.bias,
                100.0 * all.bias_std_error,
                pct(&by_vertex[0]),
                pct(&by_vertex[1]),
                pct(&by_vertex[2]),
                100.0 * all.cloud_abs_bias_median,
                100.0 * all.cloud_abs_bias_p90,
                100.0 * all.point_rmse
            );
            rows.push(PointsRow { data: dir.display().to_string(), model: name.clone(), all, by_vertex });
        }
    }
    Ok(rows)
}

//! A data set's manifest (`manifest.json`): the format, the code version, every
//! setting, the shard, completion and counts. One generic [`Manifest`] serves both
//! generators; the settings type ([`DataSpec`]) names the format and adds the fields
//! particular to its data set.

use super::npy;
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum DatagenError {
    #[error("{flag}: {why}")]
    Setting { flag: &'static str, why: String },
    #[error(transparent)]
    Npy(#[from] npy::NpyError),
    #[error("{path}: {why}")]
    File { path: PathBuf, why: String },
    /// A chunk that does not hold what it should (the message names it).
    #[error("{why}; run the generator on its shard again to make it anew")]
    Chunk { why: String },
    #[error("{dir} already holds a data set made with other settings: {diff}; use another --out or the same settings")]
    Mismatch { dir: PathBuf, diff: String },
    #[error("cancelled; {done} of {total} chunks are on disk, run the same command again to resume")]
    Cancelled { done: usize, total: usize },
}

pub(crate) fn setting(flag: &'static str, why: impl Into<String>) -> DatagenError {
    DatagenError::Setting { flag, why: why.into() }
}

/// The `format` tag of `dir/manifest.json`, or None where there is no readable
/// manifest (so a caller can pick the data set's type before loading it).
pub fn format_of(dir: &Path) -> Option<String> {
    #[derive(Deserialize)]
    struct Tag {
        format: String,
    }
    let text = std::fs::read_to_string(dir.join("manifest.json")).ok()?;
    serde_json::from_str::<Tag>(&text).ok().map(|t| t.format)
}

/// Checks a range setting: not empty, both ends `ok` (`what` says where they must lie).
pub fn check_range(flag: &'static str, r: [f32; 2], ok: impl Fn(f32) -> bool, what: &str) -> Result<(), DatagenError> {
    if !(r[0] <= r[1]) {
        Err(setting(flag, format!("{}..{} is an empty range", r[0], r[1])))
    } else if !ok(r[0]) || !ok(r[1]) {
        Err(setting(flag, format!("{}..{} must lie in {what}", r[0], r[1])))
    } else {
        Ok(())
    }
}

/// Parses "MIN..MAX" or a single value.
pub fn parse_range(flag: &'static str, s: &str) -> Result<[f32; 2], DatagenError> {
    let parse = |t: &str| {
        t.trim()
            .parse::<f32>()
            .ok()
            .filter(|v| v.is_finite())
            .ok_or_else(|| setting(flag, format!("{t:?} is not a number")))
    };
    let r = match s.split_once("..") {
        Some((a, b)) => [parse(a)?, parse(b)?],
        None => [parse(s)?; 2],
    };
    if r[0] > r[1] {
        return Err(setting(flag, format!("{s} is an empty range (MIN > MAX)")));
    }
    Ok(r)
}

/// Which part of the data set a run makes: chunks c with c mod count == index.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Shard {
    pub index: u64,
    pub count: u64,
}

impl Shard {
    pub const ALL: Shard = Shard { index: 0, count: 1 };

    /// "i/N".
    pub fn parse(s: &str) -> Result<Shard, DatagenError> {
        let bad = || setting("--shard", format!("{s:?} is not i/N with 0 <= i < N"));
        let (i, n) = s.split_once('/').ok_or_else(bad)?;
        let (index, count) = (i.trim().parse::<u64>().map_err(|_| bad())?, n.trim().parse::<u64>().map_err(|_| bad())?);
        if count == 0 || index >= count {
            return Err(bad());
        }
        Ok(Shard { index, count })
    }

    pub fn owns(&self, chunk: u64) -> bool {
        chunk % self.count == self.index
    }
}

#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct Counts {
    pub points: u64,
    pub chunks: u64,
    pub path_samples: u64,
    /// Wall-clock seconds of generation summed over runs (resumes and shards).
    pub seconds: f64,
}

/// The settings of a data set: everything its points are a function of (with the
/// seed), compared on resume and merge, and what names and cuts the data set.
pub trait DataSpec: Clone + PartialEq + Serialize + DeserializeOwned + Sync {
    /// The manifest's `format` tag and version.
    const FORMAT: &'static str;
    const FORMAT_VERSION: u32;
    /// What a manifest of this format is, for messages ("a Nimbus data-set manifest").
    const WHAT: &'static str;
    /// Columns of targets.npy.
    const TARGET_COLUMNS: [&'static str; 5];
    /// Manifest fields particular to this data set, written after `shard`.
    type Header: Clone + std::fmt::Debug + Serialize + DeserializeOwned;
    /// Checks every setting; the error names the command-line flag.
    fn validate(&self) -> Result<(), DatagenError>;
    fn header(&self) -> Self::Header;
    fn points(&self) -> u64;
    /// Points per chunk file (the unit of resuming and sharding).
    fn chunk_size(&self) -> u64;
    /// Rows each point writes.
    fn rows_per_point(&self) -> u64;
    /// Feature values per row (the chunks hold them and the 5 targets).
    fn n_features(&self) -> usize;
    /// Path samples of a merged data set, from its shards' manifests and targets.
    fn merged_path_samples(manifests: &[Manifest<Self>], targets: &[f32]) -> u64;

    /// Chunks that hold the points.
    fn n_chunks(&self) -> u64 {
        self.points().div_ceil(self.chunk_size())
    }
    /// Points in chunk `c` (the last chunk may be short).
    fn chunk_len(&self, c: u64) -> u64 {
        (self.points() - c * self.chunk_size()).min(self.chunk_size())
    }
    /// Points that `shard` makes (it owns chunks c with c mod N == i).
    fn shard_points(&self, shard: Shard) -> u64 {
        (0..self.n_chunks()).filter(|&c| shard.owns(c)).map(|c| self.chunk_len(c)).sum()
    }
}

/// manifest.json
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(bound = "S: DataSpec")]
pub struct Manifest<S: DataSpec> {
    pub format: String,
    pub format_version: u32,
    /// Nimbus version and commit that made the data.
    pub code_version: String,
    pub settings: S,
    /// The part of the data set in this directory (absent once merged / complete).
    pub shard: Option<Shard>,
    #[serde(flatten)]
    pub header: S::Header,
    pub target_columns: Vec<String>,
    /// Set once features.npy and targets.npy hold the whole data set.
    pub complete: bool,
    pub counts: Counts,
}

impl<S: DataSpec> Manifest<S> {
    pub fn new(spec: &S, shard: Option<Shard>, code_version: &str) -> Self {
        Manifest {
            format: S::FORMAT.into(),
            format_version: S::FORMAT_VERSION,
            code_version: code_version.into(),
            settings: spec.clone(),
            shard,
            header: spec.header(),
            target_columns: S::TARGET_COLUMNS.iter().map(|s| s.to_string()).collect(),
            complete: false,
            counts: Counts::default(),
        }
    }

    /// Reads `dir/manifest.json` (see [`Manifest::from_json`]).
    pub fn load(dir: &Path) -> Result<Self, DatagenError> {
        let path = dir.join("manifest.json");
        let text = std::fs::read_to_string(&path)
            .map_err(|e| DatagenError::File { path: path.clone(), why: e.to_string() })?;
        Self::from_json(&text, &path)
    }

    /// A manifest from its text (`path` names it in messages): checks its format and
    /// version and that its settings are valid, so that nothing computed from them
    /// later (chunk counts, shapes) can fail.
    pub fn from_json(text: &str, path: &Path) -> Result<Self, DatagenError> {
        let m: Self = serde_json::from_str(text)
            .map_err(|e| DatagenError::File { path: path.to_owned(), why: format!("not {}: {e}", S::WHAT) })?;
        let (f, v, format, version) = (&m.format, m.format_version, S::FORMAT, S::FORMAT_VERSION);
        if f != format || v != version {
            return Err(DatagenError::File {
                path: path.to_owned(),
                why: format!("format {f} v{v} is not {format} v{version}"),
            });
        }
        m.settings
            .validate()
            .map_err(|e| DatagenError::File { path: path.to_owned(), why: format!("settings: {e}") })?;
        Ok(m)
    }

    /// Writes `dir/manifest.json` atomically.
    pub fn save(&self, dir: &Path) -> Result<(), DatagenError> {
        let path = dir.join("manifest.json");
        let text = serde_json::to_string_pretty(self).expect("manifest serializes");
        npy::write_bytes_atomically(&path, text.as_bytes()).map_err(|e| DatagenError::Npy(npy::NpyError::Write(e)))
    }

    /// Opens `dir`'s manifest to resume it (refusing other settings or another shard,
    /// naming the flags), or creates it.
    pub fn open(dir: &Path, spec: &S, shard: Shard, code_version: &str) -> Result<Self, DatagenError> {
        let shard = (shard != Shard::ALL).then_some(shard);
        if !dir.join("manifest.json").exists() {
            let m = Self::new(spec, shard, code_version);
            m.save(dir)?;
            return Ok(m);
        }
        let m = Self::load(dir)?;
        if let Some(diff) = settings_diff(&m.settings, spec) {
            return Err(DatagenError::Mismatch { dir: dir.to_owned(), diff });
        }
        if m.shard != shard {
            return Err(DatagenError::Mismatch {
                dir: dir.to_owned(),
                diff: format!("--shard was {:?}, now {:?}", m.shard, shard),
            });
        }
        Ok(m)
    }
}

/// The settings that differ, as "--flag was A, now B".
pub fn settings_diff<T: Serialize>(old: &T, new: &T) -> Option<String> {
    let (a, b) = (serde_json::to_value(old).unwrap(), serde_json::to_value(new).unwrap());
    let (a, b) = (a.as_object().unwrap(), b.as_object().unwrap());
    let diffs: Vec<String> = b
        .iter()
        .filter(|(k, v)| a.get(*k) != Some(*v))
        .map(|(k, v)| format!("--{} was {}, now {}", k.replace('_', "-"), a.get(k).cloned().unwrap_or_default(), v))
        .collect();
    (!diffs.is_empty()).then(|| diffs.join("; "))
}

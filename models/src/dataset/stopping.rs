//! The confidence-interval stopping rule both ground-truth estimators use (thesis
//! 2.2.6): samples are added in batches until the interval's relative half-width is
//! small enough, with a floor and a ceiling on the count.

use super::manifest::{DatagenError, setting};
use engine::stats::Welford;

/// When to stop adding samples.
#[derive(Clone, Copy, Debug)]
pub struct Stopping {
    /// Maximum relative half-width of the confidence interval (thesis default 0.05).
    pub max_rel_error: f64,
    /// z of the confidence level (1.96 for 95 %).
    pub z: f64,
    pub min_samples: u64,
    pub max_samples: u64,
}

impl Default for Stopping {
    fn default() -> Self {
        Stopping { max_rel_error: 0.05, z: 1.96, min_samples: 1_000, max_samples: 10_000_000 }
    }
}

/// One estimate and its uncertainty.
#[derive(Clone, Copy, Debug)]
pub struct Estimate {
    pub mean: f64,
    pub std_error: f64,
    pub samples: u64,
}

impl Stopping {
    /// The rule for a two-sided `confidence` level in (0, 1).
    pub fn new(max_rel_error: f64, confidence: f64, min_samples: u64, max_samples: u64) -> Stopping {
        let z = engine::stats::normal_quantile(0.5 + 0.5 * confidence);
        Stopping { max_rel_error, z, min_samples, max_samples }
    }

    /// Checks a data set's stopping settings; the error names the command-line flag.
    pub fn validate(
        max_rel_error: f64,
        confidence: f64,
        min_samples: u64,
        max_samples: u64,
    ) -> Result<(), DatagenError> {
        if !(max_rel_error > 0.0 && max_rel_error < 1.0) {
            return Err(setting("--max-rel-error", format!("{max_rel_error} must lie in (0, 1)")));
        }
        if !(confidence > 0.0 && confidence < 1.0) {
            return Err(setting("--confidence", format!("{confidence} must lie in (0, 1)")));
        }
        if min_samples == 0 || min_samples > max_samples {
            return Err(setting("--min-samples", "must be at least 1 and at most --max-samples"));
        }
        Ok(())
    }

    /// Draws `sample` in batches of `batch`, checking between batches, until
    /// z * se <= max_rel_error * mean with at least `min_samples`, or `max_samples`.
    pub fn estimate(&self, batch: usize, mut sample: impl FnMut() -> f64) -> Estimate {
        let mut w = Welford::default();
        loop {
            for _ in 0..batch {
                w.add(sample());
            }
            let done = w.n >= self.min_samples && w.mean > 0.0 && self.z * w.std_error() <= self.max_rel_error * w.mean;
            if done || w.n >= self.max_samples {
                return Estimate { mean: w.mean, std_error: w.std_error(), samples: w.n };
            }
        }
    }
}

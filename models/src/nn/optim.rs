//! Training pieces both trainers share: the optimizers (SGD with momentum, Adam) and
//! their state over candle variables, the check of a training schedule, and the
//! safetensors files the weights and checkpoints go to.

use candle_core::{Tensor, Var};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::Path;

/// Writes named tensors as a safetensors file, atomically, with the permissions of
/// every other output. The file is serialized in memory: candle's own writer goes
/// through a temporary file of mode 0600 that it leaves behind when killed.
pub fn save_safetensors(tensors: &HashMap<String, Tensor>, path: &Path) -> std::io::Result<()> {
    let bytes = safetensors::serialize(tensors.iter(), None)
        .map_err(|e| std::io::Error::other(format!("cannot write {}: {e}", path.display())))?;
    crate::dataset::npy::write_bytes_atomically(path, &bytes)
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase", tag = "kind")]
pub enum Optimizer {
    /// Stochastic gradient descent with momentum (the thesis's choice).
    Sgd { momentum: f64 },
    /// Adam (beta1 0.9, beta2 0.999, eps 1e-8).
    Adam,
}

/// The schedule settings both trainers share (epochs, batch, learning rate and its
/// decay per epoch, test fraction): the flag of the first bad one and why.
pub fn check_schedule(
    epochs: usize,
    batch: usize,
    lr: f64,
    lr_decay: f64,
    test_fraction: f64,
) -> Result<(), (&'static str, &'static str)> {
    if epochs == 0 {
        return Err(("--epochs", "must be at least 1"));
    }
    if batch == 0 {
        return Err(("--batch", "must be at least 1"));
    }
    if !(lr > 0.0 && lr.is_finite()) {
        return Err(("--lr", "must be positive"));
    }
    if !(lr_decay > 0.0 && lr_decay <= 1.0) {
        return Err(("--lr-decay", "must lie in (0, 1]"));
    }
    if !(test_fraction > 0.0 && test_fraction < 1.0) {
        return Err(("--test-fraction", "must lie in (0, 1)"));
    }
    Ok(())
}

/// Optimizer state: one or two moment tensors per parameter.
pub(crate) struct OptState {
    pub(crate) step: u64,
    pub(crate) m: Vec<Tensor>,
    pub(crate) v: Vec<Tensor>,
}

impl OptState {
    pub(crate) fn new(vars: &[&Var]) -> candle_core::Result<Self> {
        let zeros = |v: &&Var| v.as_tensor().zeros_like();
        Ok(OptState {
            step: 0,
            m: vars.iter().map(zeros).collect::<Result<_, _>>()?,
            v: vars.iter().map(zeros).collect::<Result<_, _>>()?,
        })
    }

    pub(crate) fn apply(
        &mut self,
        opt: Optimizer,
        lr: f64,
        vars: &[&Var],
        grads: &candle_core::backprop::GradStore,
    ) -> candle_core::Result<()> {
        self.step += 1;
        for (k, var) in vars.iter().enumerate() {
            let Some(g) = grads.get(var.as_tensor()) else { continue };
            match opt {
                Optimizer::Sgd { momentum } => {
                    self.m[k] = ((&self.m[k] * momentum)? + g)?;
                    var.set(&(var.as_tensor() - (&self.m[k] * lr)?)?)?;
                }
                Optimizer::Adam => {
                    let (b1, b2, eps) = (0.9f64, 0.999f64, 1e-8f64);
                    self.m[k] = ((&self.m[k] * b1)? + (g * (1.0 - b1))?)?;
                    self.v[k] = ((&self.v[k] * b2)? + (g.sqr()? * (1.0 - b2))?)?;
                    let mhat = (&self.m[k] / (1.0 - b1.powi(self.step as i32)))?;
                    let vhat = (&self.v[k] / (1.0 - b2.powi(self.step as i32)))?;
                    let update = (mhat / (vhat.sqrt()? + eps)?)?;
                    var.set(&(var.as_tensor() - (update * lr)?)?)?;
                }
            }
        }
        Ok(())
    }
}

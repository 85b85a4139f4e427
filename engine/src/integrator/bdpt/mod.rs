//! Volumetric bidirectional path tracing (Veach 1997, ch. 10; Lafortune and Willems
//! 1996 for participating media) for a heterogeneous cloud in vacuum, a directional
//! sun (optionally a small cone), a constant sky and a pinhole camera.
//!
//! Each camera sample traces one light subpath and one camera subpath:
//! - the light subpath starts on a disk perpendicular to the sun that covers the
//!   cloud's bounding sphere (a parallel beam, area pdf 1 / (pi R^2)) and scatters by
//!   delta tracking and phase sampling, up to `max_light_vertices` vertices; it is
//!   traced only once the camera ray has hit the cloud;
//! - the camera subpath is the path tracer's walk; at every vertex it does next event
//!   estimation toward the sun and, at its first `max_camera_connect` vertices,
//!   connects to every light vertex through a ratio-tracked segment.
//!
//! A path with n scattering vertices can come from n strategies ([`mis`]). Light
//! tracing onto the image (no camera vertex but the lens) is not used: it needs
//! splatting into arbitrary pixels, and a cloud seen from outside rarely gains from
//! it. The sun is reached only by next event estimation and connections, the sky
//! only by escaping camera paths (weight one). A path with n scattering vertices is
//! order n and goes to the low or high buffer by k.
//!
//! Parameters ([`BdptSettings`]): `heuristic` balance or power (default power);
//! `max_camera_connect` camera vertices that connect, >= 1 (default 8);
//! `max_light_vertices` light subpath length, 1 ..= [`MAX_LIGHT_VERTICES`] (default 8).
//!
//! **Prediction mode** (thesis 6.4, [`Prediction`]). The light subpath stops after k
//! segments (y_1 .. y_k) and BDPT makes exactly the orders 1 ..= 2k, into the low
//! buffer, with the MIS weights of that capped strategy set. The camera walk goes on
//! to x_{2k} for them: stopped at x_k, the order-2k paths would have only the
//! connection x_k <-> y_k, whose unweighted 1/d^2 has infinite variance in a volume.
//! Every longer path is x_1 .. x_k, at least one vertex in between, then y_k .. y_1;
//! their sum over the middle part is the point-to-point transport T(y_k <-> x_k)
//! minus its one-segment term (the order-2k path BDPT already made). The high buffer
//! gets L_sun beta_x beta_y A (T_pred - T_1), T_pred from a [`TransportPredictor`]
//! and T_1 the one-segment term with the transmittance the 2k connection used. So in
//! this mode the buffers split at order 2k + 1: low = 1 ..= 2k, high = 2k + 1 and up.
//! The high term is evaluated with probability p and weighted 1/p. Sky light of
//! orders above 2k is not added: the predictor answers for the sun.
//!
//! Parameters of the prediction ([`Prediction`]): `segments` k, 1 ..=
//! [`MAX_LIGHT_VERTICES`]; `r` the distance threshold in world units, >= 0 (default
//! [`Prediction::DEFAULT_R`] = 0.04, the thesis's 0.08 is [`Prediction::THESIS_R`];
//! infinity extends every pair); `p` in (0, 1]; `candidates` 1 ..=
//! [`Prediction::MAX_CANDIDATES`] (default 256); `extension_samples` 1 ..=
//! [`Prediction::MAX_EXTENSION_SAMPLES`] (default 8).
//!
//! - **Close pairs.** End vertices closer than r are not predicted (the network's
//!   answer grows like 1/d^2 there and would dominate the variance). The subpaths are
//!   extended instead by the point-to-point estimator of [`crate::integrator::p2p`],
//!   averaged over `extension_samples` samples, which keeps the mode exact up to the
//!   network's error (the thesis dropped these pairs).
//! - **Light subpath candidates** (M = `candidates`). The camera end vertex is offered
//!   its own light subpath and M - 1 more, and one is chosen by resampled importance
//!   sampling on the unoccluded one-segment term, its 1/d^2 replaced below r by
//!   1 / (r max(d, r/8)) (the transport between close points grows like 1/d). One
//!   prediction serves one camera sample. The renderer traces one [`LightPool`] of
//!   light subpaths per pass (one per pixel) and the M - 1 are uniform picks from it,
//!   so a candidate costs a weight, not a subpath. Each candidate is distributed as a
//!   sample's own subpath, so the estimate stays unbiased; the samples of one pass
//!   are correlated through the pool (passes are independent). M = 1 is the thesis's
//!   pairing.
//! - **Batched predictions.** The renderer defers a tile's predictions
//!   ([`DeferredPrediction`], each with its own random stream) and asks the predictor
//!   for them at once ([`TransportPredictor::predict_batch`]); immediate and deferred
//!   evaluation give the same estimate.
//!
//! docs/point-to-point.md has the measurements behind the defaults.

pub mod mis;
pub mod prediction;
pub mod subpath;
pub mod trace;

pub use prediction::{DeferredPrediction, LightPool, Prediction, resolve_deferred};
pub use subpath::{BdptSettings, Contribution, MAX_LIGHT_VERTICES, Strategy};
pub use trace::{trace, trace_strategies};

#[cfg(doc)]
use crate::predictor::TransportPredictor;

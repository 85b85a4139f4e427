//! The scene a render reads: the medium, the lights and the camera.

use crate::camera::Camera;
use crate::light::{Sky, Sun};
use crate::medium::Medium;

/// Everything a render reads: immutable once built, shared between threads.
#[derive(Clone, Debug)]
pub struct Scene {
    pub medium: Medium,
    pub sun: Option<Sun>,
    pub sky: Sky,
    pub camera: Camera,
}

//! What the thread that changes things shares with the threads that work: the
//! generation counter every change bumps and the stop flag ([`RenderControl`]), and
//! the handle long set-up work checks to give up on a superseded generation
//! ([`Cancel`]). Its own module, below everything that checks it (render passes,
//! fields), so that neither depends on the other.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

/// Shared between the thread that changes things and the threads that render: a
/// generation counter that every scene change bumps, and a stop flag.
#[derive(Debug, Default)]
pub struct RenderControl {
    generation: AtomicU64,
    stop: AtomicBool,
}

impl RenderControl {
    pub fn new() -> Self {
        Self::default()
    }
    pub fn generation(&self) -> u64 {
        self.generation.load(Ordering::Acquire)
    }
    /// Invalidates the pass under way; returns the new generation.
    pub fn bump(&self) -> u64 {
        self.generation.fetch_add(1, Ordering::AcqRel) + 1
    }
    pub fn request_stop(&self) {
        self.stop.store(true, Ordering::Release);
    }
    pub fn clear_stop(&self) {
        self.stop.store(false, Ordering::Release);
    }
    pub fn stop_requested(&self) -> bool {
        self.stop.load(Ordering::Acquire)
    }
    /// True if a pass started in `generation` must stop.
    #[inline]
    pub fn should_abort(&self, generation: u64) -> bool {
        self.stop_requested() || self.generation() != generation
    }
}

/// Lets set-up work that takes longer than a frame (fields built per cloud and sun)
/// give up when the render it is for has been superseded: a [`RenderControl`] and the
/// generation the work belongs to, as a pass checks them. [`Cancel::NEVER`] is work
/// that always finishes.
#[derive(Clone, Copy, Debug)]
pub struct Cancel<'a>(Option<(&'a RenderControl, u64)>);

impl<'a> Cancel<'a> {
    /// Never cancelled.
    pub const NEVER: Cancel<'static> = Cancel(None);

    /// Cancelled when `control` moves past `generation` or a stop is requested.
    pub fn on(control: &'a RenderControl, generation: u64) -> Self {
        Cancel(Some((control, generation)))
    }

    /// Whether the work should stop now.
    #[inline]
    pub fn requested(&self) -> bool {
        self.0.is_some_and(|(c, g)| c.should_abort(g))
    }
}

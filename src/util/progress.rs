//! Progress of a long step as the library reports it: named phases and units of work done. The
//! command line draws it (progress bars); a program embedding the library passes its own, or
//! [`Silent`].

/// Receives the progress of a long step; called from worker threads too.
pub trait StepProgress: Sync {
    /// A phase named `name` begins with `total` units of work (0: not counted).
    fn phase(&self, name: &str, total: u64);
    /// `n` more units of the current phase are done.
    fn advance(&self, n: u64);
    /// The current phase turned out to have `more` units of work besides.
    fn grow(&self, more: u64);
}

/// Progress reported to no one.
pub struct Silent;

impl StepProgress for Silent {
    fn phase(&self, _: &str, _: u64) {}
    fn advance(&self, _: u64) {}
    fn grow(&self, _: u64) {}
}

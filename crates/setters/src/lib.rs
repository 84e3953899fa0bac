//! Chainable setters for the public fields of options and data structs, so that they can be
//! `#[non_exhaustive]` (a new field breaks no user's code) and still be built outside their
//! crate, where a struct literal cannot be written:
//! `NewtonOptions::default().rel(1e-8).max_iterations(50)`. Every deform crate that gives
//! its structs setters uses it; `deform_integrator::setters!` names the same macro.
//!
//! ```
//! #[derive(Default)]
//! #[non_exhaustive]
//! pub struct Options {
//!     pub tolerance: f64,
//!     pub steps: usize,
//! }
//! deform_setters::setters!(Options { tolerance: f64, steps: usize });
//!
//! let o = Options::default().tolerance(1e-8).steps(3);
//! assert_eq!((o.tolerance, o.steps), (1e-8, 3));
//! ```
#![no_std]
/// Implements, for each listed field of a struct, a method of the field's name that sets
/// it and returns the struct.
#[macro_export]
macro_rules! setters {
    ($ty:ty { $($field:ident: $fty:ty),* $(,)? }) => {
        impl $ty {
            $(
                #[doc = concat!("Sets `", stringify!($field), "` (see the field) and returns the value.")]
                #[must_use]
                pub fn $field(mut self, value: $fty) -> Self {
                    self.$field = value;
                    self
                }
            )*
        }
    };
}

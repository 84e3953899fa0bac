//! Chainable setters for the public fields of options and data structs, so that they can be
//! `#[non_exhaustive]` (a new field breaks no user's code) and still be built outside their
//! crate, where a struct literal cannot be written:
//! `NewtonOptions::default().rel(1e-8).max_iterations(50)`. The crates above use it too.

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

//! One module per subcommand.
pub mod demo;
pub mod eval;
pub mod experiment;
pub mod inspect;
pub mod keygen;
pub mod render;
pub mod synth;
pub mod train;

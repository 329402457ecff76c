//! One module per subcommand.
pub mod synth;
pub mod train;
pub mod render;
pub mod eval;
pub mod inspect;
pub mod keygen;
pub mod demo;
pub mod experiment;

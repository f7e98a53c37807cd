//! Subcommands other than `serve`.

pub mod bench;
pub mod domains;
pub mod inspect;
pub mod render;
pub mod train;

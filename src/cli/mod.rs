//! Subcommands other than `serve`.

pub mod bench;
pub mod inspect;

//! cutsim-load: the load and fault test of cutsim-server (the `cutsim-load` binary), and
//! the client parts it shares with the end-to-end tests.

pub mod viewer;

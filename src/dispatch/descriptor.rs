//! (being written)
use super::table::Implemented;

pub fn commands() -> Vec<Implemented> {
    vec![]
}

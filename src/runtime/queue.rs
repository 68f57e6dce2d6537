//! Queues: each has a worker thread that executes submissions in order.
use std::sync::Weak;

use crate::dispatch::handle::DispatchTag;

use super::Device;

pub struct Queue {
    pub device: Weak<Device>,
    pub family: u32,
    pub index: u32,
}

impl DispatchTag for Queue {
    const TAG: u64 = 0x4152_424f_5251_5545; // "ARBORQUE"
}

impl Queue {
    pub fn new(device: Weak<Device>, family: u32, index: u32) -> Queue {
        Queue { device, family, index }
    }
}

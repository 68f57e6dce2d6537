//! The emulated device: allocations, the device-address space, checked reads and writes.
//! Every read and write of device memory by the driver goes through this module.

/// The device-address space of one device.
pub struct AddressSpace {
    pub heap_size: u64,
}

impl AddressSpace {
    pub fn new(heap_size: u64) -> AddressSpace {
        AddressSpace { heap_size }
    }
}

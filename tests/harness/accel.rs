//! Helpers for acceleration-structure API tests: buffers with device addresses, one-shot
//! submissions, BLAS/TLAS builds of meshes, serialization read-back.

use ash::vk;

use super::Context;

pub struct Buf {
    pub buffer: vk::Buffer,
    pub memory: vk::DeviceMemory,
    pub ptr: *mut u8,
    pub address: u64,
    pub size: u64,
}

impl Buf {
    pub fn write(&self, offset: usize, data: &[u8]) {
        assert!(offset + data.len() <= self.size as usize);
        // SAFETY: mapped host-visible memory of `size` bytes.
        unsafe { std::ptr::copy_nonoverlapping(data.as_ptr(), self.ptr.add(offset), data.len()) };
    }
    pub fn read(&self, offset: usize, len: usize) -> Vec<u8> {
        assert!(offset + len <= self.size as usize);
        // SAFETY: mapped host-visible memory of `size` bytes.
        unsafe { std::slice::from_raw_parts(self.ptr.add(offset), len).to_vec() }
    }
}

pub const ALL_USAGE: vk::BufferUsageFlags = vk::BufferUsageFlags::from_raw(
    vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS.as_raw()
        | vk::BufferUsageFlags::STORAGE_BUFFER.as_raw()
        | vk::BufferUsageFlags::TRANSFER_SRC.as_raw()
        | vk::BufferUsageFlags::TRANSFER_DST.as_raw()
        | vk::BufferUsageFlags::INDIRECT_BUFFER.as_raw()
        | vk::BufferUsageFlags::ACCELERATION_STRUCTURE_BUILD_INPUT_READ_ONLY_KHR.as_raw()
        | vk::BufferUsageFlags::ACCELERATION_STRUCTURE_STORAGE_KHR.as_raw(),
);

pub struct Accel<'c> {
    pub ctx: &'c Context,
    pub ext: ash::khr::acceleration_structure::Device,
    pub deferred: ash::khr::deferred_host_operations::Device,
    pub bda: ash::khr::buffer_device_address::Device,
    pub pool: vk::CommandPool,
    /// Queue index submissions go to (one thread per queue: queues are externally synchronized).
    pub queue: usize,
    buffers: std::cell::RefCell<Vec<Buf>>,
    structures: std::cell::RefCell<Vec<vk::AccelerationStructureKHR>>,
}

impl<'c> Accel<'c> {
    pub fn new(ctx: &'c Context) -> Self {
        let ext = ash::khr::acceleration_structure::Device::new(&ctx.instance, &ctx.device);
        let deferred = ash::khr::deferred_host_operations::Device::new(&ctx.instance, &ctx.device);
        // SAFETY: valid create info.
        let pool = unsafe {
            ctx.device.create_command_pool(
                &vk::CommandPoolCreateInfo::default().flags(vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER),
                None,
            )
        }
        .unwrap();
        let bda = ash::khr::buffer_device_address::Device::new(&ctx.instance, &ctx.device);
        Accel { ctx, ext, deferred, bda, pool, queue: 0, buffers: Default::default(), structures: Default::default() }
    }

    /// A host-visible buffer with a device address, usable for every AS role. Owned by `self`.
    pub fn buffer(&self, size: u64) -> usize {
        self.buffer_with(size, ALL_USAGE)
    }

    pub fn buffer_with(&self, size: u64, usage: vk::BufferUsageFlags) -> usize {
        let (buffer, memory, ptr) = self.ctx.host_buffer(size.max(4), usage | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS);
        // SAFETY: buffer with SHADER_DEVICE_ADDRESS usage bound to DEVICE_ADDRESS memory.
        let address = unsafe { self.bda.get_buffer_device_address(&vk::BufferDeviceAddressInfo::default().buffer(buffer)) };
        let mut b = self.buffers.borrow_mut();
        b.push(Buf { buffer, memory, ptr, address, size: size.max(4) });
        b.len() - 1
    }

    pub fn buf(&self, i: usize) -> std::cell::Ref<'_, Buf> {
        std::cell::Ref::map(self.buffers.borrow(), |b| &b[i])
    }

    pub fn upload(&self, data: &[u8]) -> usize {
        let i = self.buffer(data.len() as u64);
        self.buf(i).write(0, data);
        i
    }

    /// An acceleration structure of `size` bytes in a buffer of its own.
    pub fn structure(&self, ty: vk::AccelerationStructureTypeKHR, size: u64) -> (vk::AccelerationStructureKHR, usize) {
        let b = self.buffer(size);
        let buffer = self.buf(b).buffer;
        let info = vk::AccelerationStructureCreateInfoKHR::default().buffer(buffer).size(size).ty(ty);
        // SAFETY: valid create info.
        let s = unsafe { self.ext.create_acceleration_structure(&info, None) }.unwrap();
        self.structures.borrow_mut().push(s);
        (s, b)
    }

    pub fn address_of(&self, s: vk::AccelerationStructureKHR) -> u64 {
        // SAFETY: live structure.
        unsafe {
            self.ext.get_acceleration_structure_device_address(
                &vk::AccelerationStructureDeviceAddressInfoKHR::default().acceleration_structure(s),
            )
        }
    }

    /// Record with `f`, submit to queue 0 and wait.
    pub fn submit(&self, f: impl FnOnce(vk::CommandBuffer)) {
        let d = &self.ctx.device;
        // SAFETY: valid pool, fence; the command buffer is freed after the wait.
        unsafe {
            let cb = d
                .allocate_command_buffers(
                    &vk::CommandBufferAllocateInfo::default().command_pool(self.pool).command_buffer_count(1),
                )
                .unwrap()[0];
            d.begin_command_buffer(cb, &vk::CommandBufferBeginInfo::default().flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT))
                .unwrap();
            f(cb);
            d.end_command_buffer(cb).unwrap();
            let fence = d.create_fence(&vk::FenceCreateInfo::default(), None).unwrap();
            let cbs = [cb];
            d.queue_submit(self.ctx.queues[self.queue], &[vk::SubmitInfo::default().command_buffers(&cbs)], fence).unwrap();
            d.wait_for_fences(&[fence], true, u64::MAX).unwrap();
            d.destroy_fence(fence, None);
            d.free_command_buffers(self.pool, &cbs);
        }
    }

    pub fn sizes(
        &self,
        build_type: vk::AccelerationStructureBuildTypeKHR,
        info: &vk::AccelerationStructureBuildGeometryInfoKHR,
        counts: &[u32],
    ) -> vk::AccelerationStructureBuildSizesInfoKHR<'static> {
        let mut s = vk::AccelerationStructureBuildSizesInfoKHR::default();
        // SAFETY: valid info and counts.
        unsafe { self.ext.get_acceleration_structure_build_sizes(build_type, info, counts, &mut s) };
        s
    }

    /// Serialize a structure (device command) and return the bytes.
    pub fn serialize(&self, s: vk::AccelerationStructureKHR) -> Vec<u8> {
        let size = self.query(s, vk::QueryType::ACCELERATION_STRUCTURE_SERIALIZATION_SIZE_KHR);
        let b = self.buffer(size);
        let addr = self.buf(b).address;
        self.submit(|cb| {
            let info = vk::CopyAccelerationStructureToMemoryInfoKHR::default()
                .src(s)
                .dst(vk::DeviceOrHostAddressKHR { device_address: addr })
                .mode(vk::CopyAccelerationStructureModeKHR::SERIALIZE);
            // SAFETY: valid info, recording command buffer.
            unsafe { self.ext.cmd_copy_acceleration_structure_to_memory(cb, &info) };
        });
        self.buf(b).read(0, size as usize)
    }

    /// One property through a query pool (device command) and vkGetQueryPoolResults.
    pub fn query(&self, s: vk::AccelerationStructureKHR, ty: vk::QueryType) -> u64 {
        let d = &self.ctx.device;
        // SAFETY: valid create info; pool destroyed below.
        let pool = unsafe { d.create_query_pool(&vk::QueryPoolCreateInfo::default().query_type(ty).query_count(1), None) }.unwrap();
        self.submit(|cb| {
            // SAFETY: recording command buffer, valid pool and structure.
            unsafe {
                d.cmd_reset_query_pool(cb, pool, 0, 1);
                self.ext.cmd_write_acceleration_structures_properties(cb, &[s], ty, pool, 0);
            }
        });
        let mut out = [0u64; 1];
        // SAFETY: valid pool.
        unsafe {
            d.get_query_pool_results(pool, 0, &mut out, vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT).unwrap();
            d.destroy_query_pool(pool, None);
        }
        out[0]
    }

    /// Destroy everything this helper created.
    pub fn destroy(self) {
        let d = &self.ctx.device;
        // SAFETY: this helper's queue is idle after the wait; objects are destroyed once.
        unsafe {
            d.queue_wait_idle(self.ctx.queues[self.queue]).unwrap();
            for s in self.structures.borrow().iter() {
                self.ext.destroy_acceleration_structure(*s, None);
            }
            for b in self.buffers.borrow().iter() {
                d.destroy_buffer(b.buffer, None);
                d.free_memory(b.memory, None);
            }
            d.destroy_command_pool(self.pool, None);
        }
    }
}

/// Triangle geometry over a vertex buffer (R32G32B32_SFLOAT, stride 12) and a u32 index buffer.
/// Addresses are device addresses, or host pointers (as u64) for host builds: the two share the
/// VkDeviceOrHostAddressConstKHR union.
pub fn triangles(vertex_address: u64, index_address: u64, max_vertex: u32) -> vk::AccelerationStructureGeometryKHR<'static> {
    vk::AccelerationStructureGeometryKHR::default()
        .geometry_type(vk::GeometryTypeKHR::TRIANGLES)
        .flags(vk::GeometryFlagsKHR::OPAQUE)
        .geometry(vk::AccelerationStructureGeometryDataKHR {
            triangles: vk::AccelerationStructureGeometryTrianglesDataKHR::default()
                .vertex_format(vk::Format::R32G32B32_SFLOAT)
                .vertex_data(vk::DeviceOrHostAddressConstKHR { device_address: vertex_address })
                .vertex_stride(12)
                .max_vertex(max_vertex)
                .index_type(vk::IndexType::UINT32)
                .index_data(vk::DeviceOrHostAddressConstKHR { device_address: index_address }),
        })
}

/// Instance geometry over a packed array of VkAccelerationStructureInstanceKHR.
pub fn instances(address: u64) -> vk::AccelerationStructureGeometryKHR<'static> {
    vk::AccelerationStructureGeometryKHR::default()
        .geometry_type(vk::GeometryTypeKHR::INSTANCES)
        .geometry(vk::AccelerationStructureGeometryDataKHR {
            instances: vk::AccelerationStructureGeometryInstancesDataKHR::default()
                .array_of_pointers(false)
                .data(vk::DeviceOrHostAddressConstKHR { device_address: address }),
        })
}

/// 64-byte instance record.
pub fn instance_record(transform: [f32; 12], custom_index: u32, mask: u8, sbt: u32, flags: u8, reference: u64) -> [u8; 64] {
    let mut b = [0u8; 64];
    for (k, v) in transform.iter().enumerate() {
        b[k * 4..k * 4 + 4].copy_from_slice(&v.to_le_bytes());
    }
    b[48..52].copy_from_slice(&((custom_index & 0xFF_FFFF) | ((mask as u32) << 24)).to_le_bytes());
    b[52..56].copy_from_slice(&((sbt & 0xFF_FFFF) | ((flags as u32) << 24)).to_le_bytes());
    b[56..64].copy_from_slice(&reference.to_le_bytes());
    b
}

/// The structure bytes inside a serialization (after the 56-byte header and N addresses).
pub fn payload(serialized: &[u8]) -> &[u8] {
    let n = u64::from_le_bytes(serialized[48..56].try_into().unwrap()) as usize;
    &serialized[56 + 8 * n..]
}

// Helpers for the negative tests (tests/vuid_*.rs, through `super::vuid`): placing structures inside larger,
// guarded buffers and comparing whole buffers before/after a command.
impl<'c> Accel<'c> {
    /// Number of buffers created through this helper so far (valid indices for `buf`).
    pub fn buffer_count(&self) -> usize {
        self.buffers.borrow().len()
    }

    /// Fill the whole of buffer `b` with `byte`.
    pub fn fill(&self, b: usize, byte: u8) {
        let buf = self.buf(b);
        // SAFETY: mapped host-visible memory of `size` bytes.
        unsafe { std::ptr::write_bytes(buf.ptr, byte, buf.size as usize) };
    }

    /// An acceleration structure of `size` bytes at `offset` (a multiple of 256) inside buffer
    /// `b`; destroyed by `destroy`.
    pub fn structure_at(&self, b: usize, offset: u64, size: u64, ty: vk::AccelerationStructureTypeKHR) -> vk::AccelerationStructureKHR {
        let buffer = self.buf(b).buffer;
        let info = vk::AccelerationStructureCreateInfoKHR::default().buffer(buffer).offset(offset).size(size).ty(ty);
        // SAFETY: valid create info.
        let s = unsafe { self.ext.create_acceleration_structure(&info, None) }.unwrap();
        self.structures.borrow_mut().push(s);
        s
    }
}

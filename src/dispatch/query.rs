//! Query pools: creation, host reads (vkGetQueryPoolResults) and host reset.
use std::ffi::c_void;
use std::sync::Arc;

use ash::vk;
use ash::vk::Handle;

use super::device::device_from;
use super::handle;
use super::table::{imp, Implemented};
use super::guard;
use crate::diag;
use crate::runtime::command::copy_results_len;
use crate::runtime::query::{QueryKind, QueryPool, RangeError, ReadFlags};
use crate::runtime::stall;
use crate::runtime::sync::{Deadline, WaitOutcome};

pub fn commands() -> Vec<Implemented> {
    vec![
        imp!(PFN_vkCreateQueryPool => create_query_pool),
        imp!(PFN_vkDestroyQueryPool => destroy_query_pool),
        imp!(PFN_vkGetQueryPoolResults => get_query_pool_results),
        imp!(PFN_vkResetQueryPool => reset_query_pool),
    ]
}

fn pool(h: vk::QueryPool, command: &str) -> Option<Arc<QueryPool>> {
    let p = handle::get::<QueryPool>(h.as_raw());
    if p.is_none() {
        diag::report(diag::Level::Error, command, &format!("queryPool {:#x} is not a valid handle", h.as_raw()));
    }
    p
}

unsafe extern "system" fn create_query_pool(
    device: vk::Device,
    p_info: *const vk::QueryPoolCreateInfo,
    _p_allocator: *const vk::AllocationCallbacks,
    p_pool: *mut vk::QueryPool,
) -> vk::Result {
    const CMD: &str = "vkCreateQueryPool";
    guard(CMD, vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        let Some(dev) = device_from(device) else { return vk::Result::ERROR_INITIALIZATION_FAILED };
        if p_info.is_null() || p_pool.is_null() {
            return vk::Result::ERROR_INITIALIZATION_FAILED;
        }
        // SAFETY: valid create info per the spec.
        let info = unsafe { &*p_info };
        if info.query_count == 0 {
            diag::vuid("VUID-VkQueryPoolCreateInfo-queryCount-02763", CMD, "queryCount must be greater than 0");
        }
        match QueryKind::from_type(info.query_type) {
            QueryKind::Timestamp => {}
            QueryKind::AccelerationStructure(t) => {
                let ext = if t == vk::QueryType::ACCELERATION_STRUCTURE_COMPACTED_SIZE_KHR || t == vk::QueryType::ACCELERATION_STRUCTURE_SERIALIZATION_SIZE_KHR {
                    "VK_KHR_acceleration_structure"
                } else {
                    "VK_KHR_ray_tracing_maintenance1"
                };
                if !dev.extension_enabled(ext) {
                    diag::vuid("VUID-VkQueryPoolCreateInfo-queryType-parameter", CMD, &format!("query type {} needs {ext}, which is not enabled", t.as_raw()));
                }
            }
            QueryKind::Unsupported(vk::QueryType::OCCLUSION) => {
                diag::report(diag::Level::Info, CMD, "occlusion query pool: Arbor has no graphics queue, so its queries can never be begun");
            }
            QueryKind::Unsupported(vk::QueryType::PIPELINE_STATISTICS) => {
                diag::vuid("VUID-VkQueryPoolCreateInfo-queryType-00791", CMD, "pipelineStatisticsQuery is not supported by Arbor");
            }
            QueryKind::Unsupported(t) => {
                diag::report(diag::Level::Warn, CMD, &format!("query type {} is not supported by Arbor; its queries can never be written", t.as_raw()));
            }
        }
        let p = Arc::new(QueryPool::new(info.query_type, info.query_count));
        // SAFETY: checked non-null.
        unsafe { *p_pool = vk::QueryPool::from_raw(handle::register(p)) };
        vk::Result::SUCCESS
    })
}

unsafe extern "system" fn destroy_query_pool(device: vk::Device, pool: vk::QueryPool, _p_allocator: *const vk::AllocationCallbacks) {
    guard("vkDestroyQueryPool", (), || {
        if device_from(device).is_some() && pool != vk::QueryPool::null() {
            // Recorded commands keep their own reference.
            handle::unregister::<QueryPool>(pool.as_raw());
        }
    })
}

// The Vulkan command's own parameters, one for one.
#[allow(clippy::too_many_arguments)]
unsafe extern "system" fn get_query_pool_results(
    device: vk::Device,
    query_pool: vk::QueryPool,
    first: u32,
    count: u32,
    data_size: usize,
    p_data: *mut c_void,
    stride: vk::DeviceSize,
    flags: vk::QueryResultFlags,
) -> vk::Result {
    const CMD: &str = "vkGetQueryPoolResults";
    guard(CMD, vk::Result::ERROR_DEVICE_LOST, || {
        let Some(dev) = device_from(device) else { return vk::Result::ERROR_DEVICE_LOST };
        let Some(p) = pool(query_pool, CMD) else { return vk::Result::ERROR_DEVICE_LOST };
        match p.check_range(first, count) {
            Err(RangeError::First) => {
                diag::vuid("VUID-vkGetQueryPoolResults-firstQuery-00813", CMD, &format!("firstQuery {first} is not less than the pool's {} queries", p.count));
                return vk::Result::SUCCESS;
            }
            Err(RangeError::Count) => {
                diag::vuid("VUID-vkGetQueryPoolResults-firstQuery-00816", CMD, &format!("firstQuery {first} + queryCount {count} exceeds the pool's {} queries", p.count));
                return vk::Result::SUCCESS;
            }
            Ok(()) => {}
        }
        let f = ReadFlags::from_vk(flags);
        if f.wide && !stride.is_multiple_of(8) {
            diag::vuid("VUID-vkGetQueryPoolResults-flags-00815", CMD, &format!("with 64_BIT, stride {stride} must be a multiple of 8"));
            return vk::Result::SUCCESS;
        }
        if !f.wide && !stride.is_multiple_of(4) {
            diag::vuid("VUID-vkGetQueryPoolResults-flags-02828", CMD, &format!("without 64_BIT, stride {stride} must be a multiple of 4"));
            return vk::Result::SUCCESS;
        }
        if f.partial && !p.kind.allows_partial() {
            diag::vuid("VUID-vkGetQueryPoolResults-queryType-00818", CMD, "PARTIAL is not allowed for this query type");
            return vk::Result::SUCCESS;
        }
        let needed = copy_results_len(count, stride, &f);
        if (data_size as u64) < needed || (count > 0 && p_data.is_null()) {
            diag::vuid("VUID-vkGetQueryPoolResults-dataSize-00817", CMD, &format!("dataSize {data_size} is less than the {needed} bytes the results need"));
            return vk::Result::SUCCESS;
        }
        if count == 0 {
            return vk::Result::SUCCESS;
        }
        if f.wait {
            // The spec lets WAIT on a query that nothing will write block forever, or end in
            // VK_ERROR_DEVICE_LOST. Arbor does neither in normal mode: once nothing pending can
            // write the queries (`runtime::stall`) it reports them and answers VK_NOT_READY, the
            // answer of a read without WAIT, so the application sees exactly which queries are
            // missing and keeps a working device; strict mode loses the device.
            match p.wait_available(first, count, Deadline::Never, Some(&dev.lost)) {
                WaitOutcome::Ready => {}
                WaitOutcome::Stalled => {
                    let missing: Vec<String> = (first..first + count).filter(|&q| !p.is_available(q)).map(|q| q.to_string()).collect();
                    let what = format!("WAIT on queries {} of query pool {:#x}, which no submitted command will write", missing.join(", "), query_pool.as_raw());
                    if stall::report(&dev, CMD, &what) {
                        return vk::Result::ERROR_DEVICE_LOST;
                    }
                }
                WaitOutcome::TimedOut | WaitOutcome::Cancelled => return vk::Result::ERROR_DEVICE_LOST,
            }
        }
        // SAFETY: pData is valid for dataSize bytes per the spec; dataSize ≥ needed, checked above.
        let out = unsafe { std::slice::from_raw_parts_mut(p_data as *mut u8, needed as usize) };
        let all = p.read_into(first, count, stride, &f, out);
        if dev.is_lost() {
            vk::Result::ERROR_DEVICE_LOST
        } else if all {
            vk::Result::SUCCESS
        } else {
            vk::Result::NOT_READY
        }
    })
}

unsafe extern "system" fn reset_query_pool(device: vk::Device, query_pool: vk::QueryPool, first: u32, count: u32) {
    const CMD: &str = "vkResetQueryPool";
    guard(CMD, (), || {
        let Some(dev) = device_from(device) else { return };
        let Some(p) = pool(query_pool, CMD) else { return };
        if !dev.features.host_query_reset {
            diag::vuid("VUID-vkResetQueryPool-None-02665", CMD, "the hostQueryReset feature is not enabled");
        }
        match p.check_range(first, count) {
            Err(RangeError::First) => diag::vuid("VUID-vkResetQueryPool-firstQuery-02666", CMD, &format!("firstQuery {first} is not less than the pool's {} queries", p.count)),
            Err(RangeError::Count) => diag::vuid("VUID-vkResetQueryPool-firstQuery-02667", CMD, &format!("firstQuery {first} + queryCount {count} exceeds the pool's {} queries", p.count)),
            Ok(()) => p.reset(first, count),
        }
    })
}

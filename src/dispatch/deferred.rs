//! VK_KHR_deferred_host_operations: entry points. The operation object and how joining
//! threads run its work are `runtime::deferred`'s; host commands that defer are in `accel`.
use std::sync::Arc;

use ash::vk;
use ash::vk::Handle;

use super::guard;
use super::handle;
use super::table::{imp, Implemented};
use crate::diag;
use crate::runtime::deferred::DeferredOperation;

pub fn commands() -> Vec<Implemented> {
    vec![
        imp!(PFN_vkCreateDeferredOperationKHR => create_deferred_operation_khr),
        imp!(PFN_vkDestroyDeferredOperationKHR => destroy_deferred_operation_khr),
        imp!(PFN_vkGetDeferredOperationMaxConcurrencyKHR => get_deferred_operation_max_concurrency_khr),
        imp!(PFN_vkGetDeferredOperationResultKHR => get_deferred_operation_result_khr),
        imp!(PFN_vkDeferredOperationJoinKHR => deferred_operation_join_khr),
    ]
}

/// `vkCreateDeferredOperationKHR`.
///
/// # Safety
/// The command's valid-usage rules hold for its pointer and handle parameters (the caller's
/// obligation under the Vulkan API contract).
unsafe extern "system" fn create_deferred_operation_khr(
    _device: vk::Device,
    _p_allocator: *const vk::AllocationCallbacks,
    p_op: *mut vk::DeferredOperationKHR,
) -> vk::Result {
    guard("vkCreateDeferredOperationKHR", vk::Result::ERROR_OUT_OF_HOST_MEMORY, || {
        if p_op.is_null() {
            return vk::Result::ERROR_INITIALIZATION_FAILED;
        }
        // SAFETY: valid output pointer.
        unsafe { *p_op = vk::DeferredOperationKHR::from_raw(handle::register(DeferredOperation::new())) };
        vk::Result::SUCCESS
    })
}

/// `vkDestroyDeferredOperationKHR`.
///
/// # Safety
/// The command's valid-usage rules hold for its pointer and handle parameters (the caller's
/// obligation under the Vulkan API contract).
unsafe extern "system" fn destroy_deferred_operation_khr(
    _device: vk::Device,
    op: vk::DeferredOperationKHR,
    _p_allocator: *const vk::AllocationCallbacks,
) {
    const CMD: &str = "vkDestroyDeferredOperationKHR";
    guard(CMD, (), || {
        if op == vk::DeferredOperationKHR::null() {
            return;
        }
        match handle::get::<DeferredOperation>(op.as_raw()) {
            Some(o) if o.is_pending() => {
                diag::vuid(&format!("VUID-{CMD}-operation-03436"), CMD, "the operation is not complete; not destroyed");
            }
            Some(_) => {
                handle::unregister::<DeferredOperation>(op.as_raw());
            }
            None => diag::vuid(&format!("VUID-{CMD}-operation-parameter"), CMD, "not a valid deferred operation"),
        }
    })
}

fn deferred_from(op: vk::DeferredOperationKHR, command: &str) -> Option<Arc<DeferredOperation>> {
    let o = handle::get::<DeferredOperation>(op.as_raw());
    if o.is_none() {
        diag::vuid(&format!("VUID-{command}-operation-parameter"), command, "not a valid deferred operation");
    }
    o
}

/// `vkGetDeferredOperationMaxConcurrencyKHR`.
///
/// # Safety
/// The command's valid-usage rules hold for its pointer and handle parameters (the caller's
/// obligation under the Vulkan API contract).
unsafe extern "system" fn get_deferred_operation_max_concurrency_khr(_device: vk::Device, op: vk::DeferredOperationKHR) -> u32 {
    guard("vkGetDeferredOperationMaxConcurrencyKHR", 0, || {
        deferred_from(op, "vkGetDeferredOperationMaxConcurrencyKHR").map_or(0, |o| o.max_concurrency())
    })
}

/// `vkGetDeferredOperationResultKHR`.
///
/// # Safety
/// The command's valid-usage rules hold for its pointer and handle parameters (the caller's
/// obligation under the Vulkan API contract).
unsafe extern "system" fn get_deferred_operation_result_khr(_device: vk::Device, op: vk::DeferredOperationKHR) -> vk::Result {
    guard("vkGetDeferredOperationResultKHR", vk::Result::ERROR_UNKNOWN, || {
        deferred_from(op, "vkGetDeferredOperationResultKHR").map_or(vk::Result::ERROR_UNKNOWN, |o| o.result())
    })
}

/// `vkDeferredOperationJoinKHR`.
///
/// # Safety
/// The command's valid-usage rules hold for its pointer and handle parameters (the caller's
/// obligation under the Vulkan API contract).
unsafe extern "system" fn deferred_operation_join_khr(_device: vk::Device, op: vk::DeferredOperationKHR) -> vk::Result {
    guard("vkDeferredOperationJoinKHR", vk::Result::ERROR_UNKNOWN, || {
        deferred_from(op, "vkDeferredOperationJoinKHR").map_or(vk::Result::ERROR_UNKNOWN, |o| o.join())
    })
}

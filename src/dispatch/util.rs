//! Raw-pointer helpers shared by the dispatch modules: pNext chains, the two-call enumerate
//! idiom, C strings.
use std::ffi::{c_char, c_void, CStr};

use ash::vk;

/// Find the first struct with `s_type` in an input pNext chain. Unknown structs are skipped.
///
/// # Safety
/// `p_next` must be null or a valid Vulkan pNext chain, and the struct with `s_type` must be a `T`.
pub unsafe fn find_in<'a, T>(mut p_next: *const c_void, s_type: vk::StructureType) -> Option<&'a T> {
    let mut guard = 0;
    while !p_next.is_null() && guard < 4096 {
        // SAFETY: every Vulkan struct starts with sType and pNext (VkBaseInStructure).
        let base = unsafe { &*(p_next as *const vk::BaseInStructure) };
        if base.s_type == s_type {
            // SAFETY: the caller guarantees the struct with this sType is a T.
            return Some(unsafe { &*(p_next as *const T) });
        }
        p_next = base.p_next as *const c_void;
        guard += 1;
    }
    None
}

/// Visit every struct of an output pNext chain (unknown ones are passed too; the visitor skips them).
///
/// # Safety
/// `p_next` must be null or a valid, writable Vulkan pNext chain.
pub unsafe fn for_each_out(mut p_next: *mut c_void, mut f: impl FnMut(vk::StructureType, *mut c_void)) {
    let mut guard = 0;
    while !p_next.is_null() && guard < 4096 {
        // SAFETY: every Vulkan struct starts with sType and pNext (VkBaseOutStructure).
        let base = unsafe { &*(p_next as *const vk::BaseOutStructure) };
        let next = base.p_next as *mut c_void;
        f(base.s_type, p_next);
        p_next = next;
        guard += 1;
    }
}

/// Write a value into an output struct of the pNext chain, keeping its sType and pNext.
///
/// # Safety
/// `dst` must point to a writable `T` whose sType matches `value`'s.
pub unsafe fn write_keep_chain<T: Copy>(dst: *mut c_void, mut value: T) {
    // SAFETY: T is a Vulkan output struct: sType then pNext at the start.
    unsafe {
        let old_next = (*(dst as *const vk::BaseOutStructure)).p_next;
        let v = &mut value as *mut T as *mut vk::BaseOutStructure;
        (*v).p_next = old_next;
        std::ptr::write(dst as *mut T, value);
    }
}

/// The two-call enumerate idiom: with a null `p_items` report the count; otherwise write up to
/// `*p_count` items and return VK_INCOMPLETE when there were more.
///
/// # Safety
/// `p_count` must be valid; `p_items` null or valid for `*p_count` writes.
pub unsafe fn enumerate<T: Copy>(items: &[T], p_count: *mut u32, p_items: *mut T) -> vk::Result {
    if p_count.is_null() {
        return vk::Result::ERROR_INITIALIZATION_FAILED;
    }
    // SAFETY: checked non-null; the caller guarantees validity.
    unsafe {
        if p_items.is_null() {
            *p_count = items.len() as u32;
            return vk::Result::SUCCESS;
        }
        let n = (*p_count as usize).min(items.len());
        std::ptr::copy_nonoverlapping(items.as_ptr(), p_items, n);
        *p_count = n as u32;
        if n < items.len() {
            vk::Result::INCOMPLETE
        } else {
            vk::Result::SUCCESS
        }
    }
}

/// Read a C string argument.
///
/// # Safety
/// `p` must be null or a valid NUL-terminated string.
pub unsafe fn cstr<'a>(p: *const c_char) -> Option<&'a str> {
    if p.is_null() {
        return None;
    }
    // SAFETY: caller guarantees a valid NUL-terminated string.
    unsafe { CStr::from_ptr(p) }.to_str().ok()
}

/// Read an array of C strings (extension names).
///
/// # Safety
/// `pp` must be null or valid for `n` pointers to NUL-terminated strings.
pub unsafe fn cstr_array(pp: *const *const c_char, n: u32) -> Vec<String> {
    if pp.is_null() {
        return Vec::new();
    }
    // SAFETY: caller guarantees `n` valid string pointers.
    (0..n as usize).filter_map(|i| unsafe { cstr(*pp.add(i)) }.map(str::to_owned)).collect()
}

/// Slice from a (pointer, count) pair; empty for null or zero.
///
/// # Safety
/// `p` must be null or valid for `n` reads of T for the returned lifetime.
pub unsafe fn slice<'a, T>(p: *const T, n: u32) -> &'a [T] {
    if p.is_null() || n == 0 {
        &[]
    } else {
        // SAFETY: caller guarantees validity.
        unsafe { std::slice::from_raw_parts(p, n as usize) }
    }
}

/// Copy a Rust string into a fixed C char array (truncating, always NUL-terminated).
pub fn write_name(dst: &mut [c_char], s: &str) {
    let n = s.len().min(dst.len().saturating_sub(1));
    for (d, b) in dst.iter_mut().zip(s.bytes().take(n)) {
        *d = b as c_char;
    }
    if let Some(z) = dst.get_mut(n) {
        *z = 0;
    }
}

/// Store an out-value through a pointer if it is not null.
///
/// # Safety
/// `p` must be null or valid for a write of T.
pub unsafe fn out<T>(p: *mut T, v: T) {
    if !p.is_null() {
        // SAFETY: checked non-null; caller guarantees validity.
        unsafe { p.write(v) }
    }
}

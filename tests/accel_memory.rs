//! Host memory of a build is O(threads): with a counting global allocator, building one million
//! triangles allocates far less than 8 bytes per primitive beyond the caller's dst/scratch.
//! (Its own test binary: the allocator counts every allocation of the process.)

mod reference;

use arbor::accel::{self, AsType, BuildDesc, BuildFlags};
use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

struct Counting;

static ENABLED: AtomicBool = AtomicBool::new(false);
static ALLOCATED: AtomicUsize = AtomicUsize::new(0);
static LIVE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);
static COUNT: AtomicUsize = AtomicUsize::new(0);

// SAFETY: forwards to the system allocator unchanged; only adds relaxed counters.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if ENABLED.load(Ordering::Relaxed) {
            ALLOCATED.fetch_add(layout.size(), Ordering::Relaxed);
            COUNT.fetch_add(1, Ordering::Relaxed);
            let live = LIVE.fetch_add(layout.size(), Ordering::Relaxed) + layout.size();
            PEAK.fetch_max(live, Ordering::Relaxed);
        }
        // SAFETY: same contract as the caller's.
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        if ENABLED.load(Ordering::Relaxed) {
            LIVE.fetch_sub(layout.size().min(LIVE.load(Ordering::Relaxed)), Ordering::Relaxed);
        }
        // SAFETY: same contract as the caller's.
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if ENABLED.load(Ordering::Relaxed) && new_size > layout.size() {
            let grow = new_size - layout.size();
            ALLOCATED.fetch_add(grow, Ordering::Relaxed);
            COUNT.fetch_add(1, Ordering::Relaxed);
            let live = LIVE.fetch_add(grow, Ordering::Relaxed) + grow;
            PEAK.fetch_max(live, Ordering::Relaxed);
        }
        // SAFETY: same contract as the caller's.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

fn reset() {
    ALLOCATED.store(0, Ordering::SeqCst);
    LIVE.store(0, Ordering::SeqCst);
    PEAK.store(0, Ordering::SeqCst);
    COUNT.store(0, Ordering::SeqCst);
}

fn measure<R>(f: impl FnOnce() -> R) -> (R, usize, usize, usize) {
    reset();
    ENABLED.store(true, Ordering::SeqCst);
    let r = f();
    ENABLED.store(false, Ordering::SeqCst);
    (r, ALLOCATED.load(Ordering::SeqCst), PEAK.load(Ordering::SeqCst), COUNT.load(Ordering::SeqCst))
}

/// One test function: the counters are global, so the measurements must not run concurrently.
#[test]
fn host_memory_is_o_threads() {
    build_of_one_million_triangles_allocates_o_threads();
    update_and_tlas_build_allocate_o_threads();
}

fn update_and_tlas_build_allocate_o_threads() {
    use arbor::accel::{GeometryData, GeometryFlags, MapView};
    use arbor_scene::InstanceRecord;
    let n = 1_000_000usize;
    let mesh = arbor_scene::random_soup(n, 2);
    let data = reference::TriData::from_mesh(&mesh, 0);
    let geoms = [data.geometry()];
    let flags = BuildFlags(BuildFlags::ALLOW_UPDATE | BuildFlags::PREFER_FAST_TRACE);
    let sizes = accel::build_sizes(AsType::BottomLevel, flags, &[reference::shape_of(&geoms[0])], &[n as u32]);
    let mut dst = vec![0u8; sizes.acceleration_structure_size as usize];
    let mut scratch = vec![0u8; sizes.build_scratch_size.max(sizes.update_scratch_size) as usize];
    let desc = BuildDesc { ty: AsType::BottomLevel, flags, geometries: &geoms };
    let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap();
    pool.install(|| rayon::join(|| (), || ()));
    pool.install(|| accel::build(&desc, &accel::NoDevice, &mut dst, &mut scratch)).expect("build");
    let (r, total, peak, count) = measure(|| pool.install(|| accel::update(&desc, &accel::NoDevice, None, &mut dst, &mut scratch[..sizes.update_scratch_size as usize])));
    r.expect("update");
    eprintln!("update of 1M: {count} allocations, {total} bytes, peak {peak}");
    assert!(total < n * 8 / 16, "update allocated {total} bytes on the host");
    // TLAS of 200k instances.
    let m = 200_000usize;
    let small = arbor_scene::random_soup(100, 3);
    let sd = reference::TriData::from_mesh(&small, 0);
    let blas = reference::build_blas(0, &[sd.geometry()]);
    let mut view = MapView::new();
    view.insert(0x1000_0000, blas.bytes);
    let packed = InstanceRecord::pack(&arbor_scene::instance_records(m, &[0x1000_0000], 4));
    let g = [accel::Geometry { flags: GeometryFlags(0), primitive_count: m as u32, data: GeometryData::Instances { array_of_pointers: false, data: &packed } }];
    let tflags = BuildFlags(BuildFlags::PREFER_FAST_TRACE);
    let tsizes = accel::build_sizes(AsType::TopLevel, tflags, &[accel::GeometryShape::Instances], &[m as u32]);
    let mut tdst = vec![0u8; tsizes.acceleration_structure_size as usize];
    let mut tscratch = vec![0u8; tsizes.build_scratch_size as usize];
    let tdesc = BuildDesc { ty: AsType::TopLevel, flags: tflags, geometries: &g };
    let (r, total, peak, count) = measure(|| pool.install(|| accel::build(&tdesc, &view, &mut tdst, &mut tscratch)));
    r.expect("TLAS build");
    eprintln!("TLAS of {m} instances: {count} allocations, {total} bytes, peak {peak}");
    assert!(total < m * 8 / 16, "TLAS build allocated {total} bytes on the host");
}

fn build_of_one_million_triangles_allocates_o_threads() {
    let n = 1_000_000usize;
    let mesh = arbor_scene::random_soup(n, 1);
    let data = reference::TriData::from_mesh(&mesh, 0);
    let geoms = [data.geometry()];
    for (threads, tier) in [(1, BuildFlags::PREFER_FAST_TRACE), (2, BuildFlags::PREFER_FAST_TRACE), (2, BuildFlags::PREFER_FAST_BUILD), (8, 0)] {
        let sizes = accel::build_sizes(AsType::BottomLevel, BuildFlags(tier), &[reference::shape_of(&geoms[0])], &[n as u32]);
        let mut dst = vec![0u8; sizes.acceleration_structure_size as usize];
        let mut scratch = vec![0u8; sizes.build_scratch_size as usize];
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        // Warm the pool (thread start-up allocations are not the build's).
        pool.install(|| rayon::join(|| (), || ()));
        let desc = BuildDesc { ty: AsType::BottomLevel, flags: BuildFlags(tier), geometries: &geoms };
        ALLOCATED.store(0, Ordering::SeqCst);
        LIVE.store(0, Ordering::SeqCst);
        PEAK.store(0, Ordering::SeqCst);
        COUNT.store(0, Ordering::SeqCst);
        ENABLED.store(true, Ordering::SeqCst);
        let report = pool.install(|| accel::build(&desc, &accel::NoDevice, &mut dst, &mut scratch));
        ENABLED.store(false, Ordering::SeqCst);
        let report = report.expect("build");
        // Degenerate soup triangles (clamped into the cube) may be dropped without ALLOW_UPDATE.
        assert!(report.primitive_count as usize <= n && report.primitive_count as usize > n - 100);
        let (total, peak, count) = (ALLOCATED.load(Ordering::SeqCst), PEAK.load(Ordering::SeqCst), COUNT.load(Ordering::SeqCst));
        eprintln!("threads {threads} tier {tier:#x}: {count} allocations, {total} bytes in total, peak live {peak} bytes (dst {} scratch {})", dst.len(), scratch.len());
        // "Far less than N x 8 bytes": a sixteenth of it (0.5 B per primitive) in total.
        assert!(total < n * 8 / 16, "threads {threads} tier {tier:#x}: build allocated {total} bytes on the host (> {} = N x 0.5 B)", n * 8 / 16);
        assert!(peak < n * 8 / 16);
        drop(pool);
    }
}

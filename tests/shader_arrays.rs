//! Arrays of buffer descriptors in the shader library (`arbor::shader`, no Vulkan device):
//! tests/shaders/vk_arrays.comp over `HostMemory` elements bound one by one — a runtime array
//! takes its length from what is bound — checked against a CPU reference; an element left
//! unbound faults naming the element, the others still run.
use std::path::PathBuf;

use arbor::shader::{dispatch, FaultKind, FaultSpace, HostMemory, Module, Pipeline, Watchdog};

fn vk_arrays() -> Pipeline {
    let src = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/shaders/vk_arrays.comp");
    let out = std::env::temp_dir().join(format!("arbor-shader-arrays-{}.spv", std::process::id()));
    let r = std::process::Command::new("glslangValidator").args(["-V", "--target-env", "vulkan1.2", "-o"]).arg(&out).arg(&src).output().expect("glslangValidator");
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stdout));
    let words: Vec<u32> = std::fs::read(&out).unwrap().chunks(4).map(|c| u32::from_le_bytes(c.try_into().unwrap())).collect();
    Pipeline::compute(&Module::parse(&words).unwrap(), "main", &[]).unwrap()
}

fn bytes(v: &[u32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

#[test]
fn buffer_arrays_over_host_memory_match_the_cpu_reference() {
    let p = vk_arrays();
    let n = 64usize;
    let (pick, shift) = (1u32, 1u32);
    let mut mem = HostMemory::new();
    let outs: Vec<usize> = (0..4).map(|_| mem.add_buffer(&[0; 64])).collect();
    for (e, &b) in outs.iter().enumerate().filter(|&(e, _)| e != 3) {
        mem.bind_element(0, 0, e as u32, b);
    }
    for e in 0..3u32 {
        let b = mem.add_buffer(&bytes(&[10 + e, 100 * (e + 1), 0, 0]));
        mem.bind_element(0, 1, e, b);
        let b = mem.add_buffer(&bytes(&(0..n as u32).map(|k| (e + 1) * 1000 + k * 7).collect::<Vec<_>>()));
        mem.bind_element(0, 2, e, b);
    }
    let report = dispatch(&p, &mem, &bytes(&[pick, shift]), [n as u32 / 16, 1, 1], [0; 3], &Watchdog::default());
    // Element 3 of the storage array is not bound: its 16 writes fault, naming it.
    assert_eq!(report.fault_count, 16, "{report:?}");
    assert!(report.faults.iter().all(|f| f.kind == FaultKind::Unbound && f.space == FaultSpace::ArrayElement { set: 0, binding: 0, element: 3 }), "{report:?}");
    for (e, &b) in outs.iter().enumerate().take(3) {
        let got: Vec<u32> = mem.bytes(b).chunks(4).map(|c| u32::from_le_bytes(c.try_into().unwrap())).collect();
        let want: Vec<u32> = (0..16)
            .map(|k| {
                let i = 4 * k + e;
                let j = (i + shift as usize) % 3;
                ((j as u32 + 1) * 1000 + i as u32 * 7) * 3 + 12 + 100 * (pick + 1) * j as u32
            })
            .collect();
        assert_eq!(got, want, "element {e}");
    }
}

// Machine probe: per-copy time of three kernels when 1, 8 or 16 copies run at once.
use std::time::Instant;
fn compute(iters: u64) -> u64 {
    // Dependent integer/float chain in registers: no memory traffic.
    let (mut x, mut f) = (0x9E3779B97F4A7C15u64, 1.0f64);
    for _ in 0..iters {
        x ^= x << 13; x ^= x >> 7; x ^= x << 17;
        f = f * 1.0000001 + (x & 0xff) as f64 * 1e-9;
    }
    x ^ f.to_bits()
}
fn cache(buf: &mut [u32], iters: u64) -> u64 {
    // Random read-modify-write in a buffer (size chosen by caller).
    let n = buf.len() as u64; let mut x = 88172645463325252u64; let mut s = 0u64;
    for _ in 0..iters { x ^= x << 13; x ^= x >> 7; x ^= x << 17; let i = (x % n) as usize; s = s.wrapping_add(buf[i] as u64); buf[i] = buf[i].wrapping_add(1); }
    s
}
fn stream(buf: &mut [u64], passes: usize) -> u64 {
    let mut s = 0u64;
    for _ in 0..passes { for v in buf.iter_mut() { s = s.wrapping_add(*v); *v = s; } }
    s
}
fn main() {
    let args: Vec<String> = std::env::args().collect();
    let kind = args[1].as_str(); let copies: usize = args[2].parse().unwrap();
    let hs: Vec<_> = (0..copies).map(|_| { let k = kind.to_string(); std::thread::spawn(move || {
        let t = Instant::now();
        let r = match k.as_str() {
            "compute" => compute(200_000_000),
            "l2" => { let mut b = vec![1u32; 256 * 1024]; cache(&mut b, 100_000_000) }
            "l3" => { let mut b = vec![1u32; 4 * 1024 * 1024]; cache(&mut b, 30_000_000) }
            _ => { let mut b = vec![1u64; 8 * 1024 * 1024]; stream(&mut b, 20) }
        };
        (t.elapsed().as_secs_f64() * 1e3, r)
    })}).collect();
    let ts: Vec<f64> = hs.into_iter().map(|h| h.join().unwrap().0).collect();
    let mean = ts.iter().sum::<f64>() / ts.len() as f64;
    println!("{kind:8} copies {copies:2}: mean {mean:7.1} ms  max {:7.1}", ts.iter().cloned().fold(0.0, f64::max));
}

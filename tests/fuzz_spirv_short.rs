//! A short run of the SPIR-V mutation fuzzer (`bench/src/fuzz_spirv.rs`, long runs with
//! `cargo run --release --bin arbor-fuzz -- --spirv`): a fixed seed, zero crashes, every
//! rejection named, and accepted mutants dispatched to a contained end.
#[path = "../bench/src/fuzz.rs"]
#[allow(dead_code)]
mod fuzz;
#[path = "../bench/src/fuzz_spirv.rs"]
mod fuzz_spirv;

#[test]
fn seeds_are_accepted_unmutated() {
    for (name, words) in fuzz_spirv::seeds() {
        let module = arbor::shader::Module::parse(&words).unwrap_or_else(|e| panic!("seed {name}: {e}"));
        arbor::shader::Pipeline::compute(&module, "main", &[]).unwrap_or_else(|e| panic!("seed {name}: {e}"));
    }
}

#[test]
fn fixed_seed_spirv_fuzz_run_has_no_crash_and_names_every_rejection() {
    let (counts, outcomes) = fuzz_spirv::run(3_000, 11);
    assert_eq!(counts.executions, 3_000);
    let rejected: u64 = counts.rejections.values().sum();
    assert_eq!(counts.accepted + rejected, counts.executions);
    assert_eq!(outcomes.values().sum::<u64>(), counts.accepted, "every accepted module was dispatched");
    assert!(counts.rejections.keys().all(|r| r.len() > "parse: ".len()), "{counts:?}");
    // Both outcomes happen: the mutants reach the executor, and the front end rejects others.
    assert!(counts.accepted > 0 && rejected > 0, "{counts:?}");
    assert!(counts.rejections.keys().any(|r| r.starts_with("parse: ")), "{counts:?}");
    assert!(outcomes.contains_key("clean"), "{outcomes:?}");
}


/// Word offsets and opcodes of a module's instructions, walked independently of the parser.
fn instructions(words: &[u32]) -> Vec<(usize, u32)> {
    let mut out = Vec::new();
    let mut at = 5;
    while at < words.len() {
        let n = (words[at] >> 16) as usize;
        out.push((at, words[at] & 0xFFFF));
        at += n.max(1);
    }
    out
}

fn words_of(bytes: &[u8]) -> Vec<u32> {
    bytes.chunks_exact(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect()
}

/// Found by `arbor-fuzz --spirv --iterations 100000 --seed 1`: an OpSMulExtended whose result
/// type is a scalar (two registers for one component) feeding OpGroupNonUniformIMul, which
/// indexed past its operand's type and was caught only by the lowering backstop. It must be a
/// rejection naming the instruction and its word offset.
#[test]
fn fuzz_found_operand_count_mismatch_is_a_named_rejection() {
    let words = words_of(include_bytes!("../bench/fuzz-seeds/crashes/smul_extended_scalar_result.spv"));
    let module = arbor::shader::Module::parse(&words).expect("the module parses; lowering rejects it");
    let err = arbor::shader::Pipeline::compute(&module, "main", &[]).expect_err("mismatched operands must be rejected");
    const OP_SMUL_EXTENDED: u32 = 152;
    let at = instructions(&words).into_iter().find(|&(_, op)| op == OP_SMUL_EXTENDED).map(|(at, _)| at).expect("the module has an OpSMulExtended");
    match &err {
        arbor::shader::ShaderError::Malformed { offset, reason } => {
            assert_eq!(*offset, at, "{err}");
            assert!(reason.contains("OpSMulExtended") && !reason.contains(fuzz_spirv::BACKSTOP), "{err}");
        }
        other => panic!("expected a malformed-module rejection, got {other}"),
    }
}

/// rspirv's parser panics on OpSpecConstantOp wrapping an opcode with an operand kind it cannot
/// read there (OpConstant's context-dependent literal; found by the 1,000,000-execution run):
/// the front end refuses such a module before rspirv sees it, naming the instruction.
#[test]
fn spec_constant_op_of_an_unfoldable_opcode_is_refused_before_decoding() {
    let (_, seed) = fuzz_spirv::seeds().into_iter().find(|(name, _)| *name == "spec_swizzle").expect("seed");
    const OP_SPEC_CONSTANT_OP: u32 = 52;
    const OP_CONSTANT: u32 = 43;
    let at = instructions(&seed).into_iter().find(|&(_, op)| op == OP_SPEC_CONSTANT_OP).map(|(at, _)| at).expect("the seed has an OpSpecConstantOp");
    let mut words = seed.clone();
    words[at + 3] = OP_CONSTANT;
    match arbor::shader::Module::parse(&words) {
        Err(arbor::shader::ShaderError::Unsupported { what, offset }) => {
            assert_eq!(offset, at);
            assert!(what.contains("OpSpecConstantOp of OpConstant"), "{what}");
        }
        other => panic!("expected the module refused, got {:?}", other.err()),
    }
}

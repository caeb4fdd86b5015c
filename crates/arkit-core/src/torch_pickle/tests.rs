use super::machine::parse_state_dict_pickle;
use super::open;
use super::tensor::TorchDType;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

fn seed(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../fuzz/corpus/torch_pickle")
        .join(name)
}

fn f32s(b: &[u8]) -> Vec<f32> {
    b.chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

fn refused(data: &[u8]) -> String {
    let t = Instant::now();
    let e = parse_state_dict_pickle(data, Path::new("x.pth"))
        .expect_err("refused")
        .to_string();
    assert!(
        t.elapsed() < Duration::from_secs(1),
        "{e}: {:?}",
        t.elapsed()
    );
    assert!(e.starts_with("x.pth"), "{e}");
    e
}

/// A file written by `torch.save` (torch 2.x; tests/python/torch_pickle_seeds.py):
/// names in order, types, shapes and every value, a transposed view read through
/// its strides.
#[test]
fn a_torch_saved_state_dict_reads_value_for_value() {
    let mut z = open(&seed("real.pth")).unwrap();
    let names: Vec<&str> = z.tensors().iter().map(|t| t.name.as_str()).collect();
    assert_eq!(names, ["a.weight", "a.num_batches_tracked", "b", "c.half"]);
    let t = &z.tensors()[2];
    assert_eq!(
        (t.dtype, t.shape.as_slice(), t.stride.as_slice()),
        (TorchDType::F32, &[4, 3][..], &[1, 4][..])
    );
    assert_eq!(f32s(&z.read(0).unwrap()), [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]);
    assert_eq!(z.tensors()[1].dtype, TorchDType::I64);
    assert!(z.tensors()[1].shape.is_empty());
    assert_eq!(z.read(1).unwrap(), 7i64.to_le_bytes());
    // b = arange(12).reshape(3, 4).t(): b[i][j] = 4 j + i.
    let want: Vec<f32> = (0..4)
        .flat_map(|i| (0..3).map(move |j| (4 * j + i) as f32))
        .collect();
    assert_eq!(f32s(&z.read(2).unwrap()), want);
    assert_eq!(z.tensors()[3].dtype, TorchDType::F16);
    // float16 1.5 = 0x3e00, -2.0 = 0xc000.
    assert_eq!(z.read(3).unwrap(), [0x00, 0x3e, 0x00, 0xc0]);
}

#[test]
fn a_module_state_dict_with_metadata_reads() {
    let z = open(&seed("module.pth")).unwrap();
    let names: Vec<&str> = z.tensors().iter().map(|t| t.name.as_str()).collect();
    assert_eq!(
        names,
        [
            "0.weight",
            "0.bias",
            "1.weight",
            "1.bias",
            "1.running_mean",
            "1.running_var",
            "1.num_batches_tracked"
        ]
    );
    assert_eq!(z.tensors()[0].shape, [3, 2, 1]);
}

/// 10^6 nested tuples (1 MB, which overflowed the stack of a recursive reader) and
/// 10^6 nested marks: refused at the depth limit, at once.
#[test]
fn deep_nesting_is_refused_at_the_limit() {
    let mut p = b"\x80\x02)".to_vec();
    p.extend(std::iter::repeat_n(0x85u8, 1_000_000));
    p.push(b'.');
    let e = refused(&p);
    assert!(e.contains("nested more than 32 deep"), "{e}");
    let mut p = b"\x80\x02".to_vec();
    p.extend(std::iter::repeat_n(b'(', 1_000_000));
    let e = refused(&p);
    assert!(e.contains("marks nested more than 32 deep"), "{e}");
    // Just at the limit is read (and refused for what it is, not for its depth).
    let mut p = b"\x80\x02)".to_vec();
    p.extend(std::iter::repeat_n(0x85u8, 31));
    p.push(b'.');
    assert!(refused(&p).contains("holds a tuple, not a state_dict"));
}

/// A memo entry replaced by a pair of itself 40 times (2^40 leaves if copied, as
/// candle's reader did) costs 40 tuples; a million times is refused by the depth
/// bound; as a dict entry it is named.
#[test]
fn memo_doubling_is_shared_not_copied() {
    let double = |n: usize| {
        let mut p = b"\x80\x02X\x01\x00\x00\x00aq\x000".to_vec();
        for _ in 0..n {
            p.extend(b"h\x00h\x00\x86q\x000");
        }
        p.extend(b"h\x00");
        p
    };
    let mut p = double(20);
    p.push(b'.');
    assert!(refused(&p).contains("holds a tuple"));
    let mut p = double(1_000_000);
    p.push(b'.');
    assert!(refused(&p).contains("nested more than 32 deep"));
    // In a dict: X = {'w': <20-fold doubled tuple>}.
    let mut p = b"\x80\x02}q\x01X\x01\x00\x00\x00w".to_vec();
    p.extend(&double(20)[2..]);
    p.extend(b"s.");
    let e = refused(&p);
    assert!(e.contains("entry 'w' is a tuple, not a tensor"), "{e}");
}

/// Pushing one memo entry millions of times hits the allocation bound.
#[test]
fn the_allocation_bound_holds() {
    let mut p = b"\x80\x02Nq\x00".to_vec();
    for _ in 0..5_000_000 {
        p.extend(b"h\x00");
    }
    p.push(b'.');
    let e = refused(&p);
    assert!(e.contains("more than 67108864 bytes of objects"), "{e}");
}

/// An entry that is not a tensor is named; so is a global outside the subset, and
/// a tensor reaching beyond its storage.
#[test]
fn what_is_not_a_state_dict_is_named() {
    let e = open(&seed("non_tensor_entry.pth")).unwrap_err().to_string();
    assert!(
        e.contains("entry 'epoch' is an integer, not a tensor"),
        "{e}"
    );
    let e = refused(b"\x80\x02cos\nsystem\nX\x02\x00\x00\x00ls\x85R.");
    assert!(e.contains("refers to os.system"), "{e}");
    let e = open(&seed("beyond_storage.pth")).unwrap_err().to_string();
    assert!(
        e.contains("reaches beyond its storage 0 of 2 elements"),
        "{e}"
    );
    let e = open(&seed("memo_doubling.pth")).unwrap_err().to_string();
    assert!(e.contains("nested more than 32 deep"), "{e}");
}

/// Every prefix of a real pickle is an error, never a panic.
#[test]
fn every_truncation_is_an_error() {
    let p = std::fs::read(seed("module.pkl")).unwrap();
    assert_eq!(
        parse_state_dict_pickle(&p, Path::new("m")).unwrap().len(),
        7
    );
    for n in 0..p.len() {
        assert!(
            parse_state_dict_pickle(&p[..n], Path::new("m")).is_err(),
            "{n}"
        );
    }
}

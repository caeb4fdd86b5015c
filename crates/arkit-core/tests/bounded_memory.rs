//! Hostile `.npy` / `.npz` files are refused with an error naming the file, and reading
//! them costs bounded memory: every case runs under a counting global allocator and the
//! peak of live heap bytes during the call is asserted. The tests of this binary take
//! turns ([`one_at_a_time`]): the allocator counts every thread, and one test's inputs
//! (an 8 MiB member, say) would otherwise count in another's peak.
//!
//! The files are crafted in memory (or as sparse files, which take no disk space).

use arkit_core::limits;
use arkit_core::{NpyArray, NpzCompression};
use std::alloc::{GlobalAlloc, Layout, System};
use std::io::Write;
use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};

struct Counting;

static LIVE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            let now = LIVE.fetch_add(layout.size(), Ordering::SeqCst) + layout.size();
            PEAK.fetch_max(now, Ordering::SeqCst);
        }
        p
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) };
        LIVE.fetch_sub(layout.size(), Ordering::SeqCst);
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            if new_size >= layout.size() {
                let now = LIVE.fetch_add(new_size - layout.size(), Ordering::SeqCst) + new_size
                    - layout.size();
                PEAK.fetch_max(now, Ordering::SeqCst);
            } else {
                LIVE.fetch_sub(layout.size() - new_size, Ordering::SeqCst);
            }
        }
        p
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// Held for the whole of each test, so that only one test allocates at a time.
fn one_at_a_time() -> std::sync::MutexGuard<'static, ()> {
    static TURN: std::sync::Mutex<()> = std::sync::Mutex::new(());
    TURN.lock().unwrap_or_else(|e| e.into_inner())
}

/// Runs `f` and returns its result with the peak heap growth (bytes) during the call.
fn peak_during<T>(f: impl FnOnce() -> T) -> (T, usize) {
    let base = LIVE.load(Ordering::SeqCst);
    PEAK.store(base, Ordering::SeqCst);
    let out = f();
    (out, PEAK.load(Ordering::SeqCst).saturating_sub(base))
}

const MIB: usize = 1 << 20;

fn crc32(data: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &b in data {
        crc ^= b as u32;
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xEDB8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

/// A one-member stored zip whose central directory claims `claimed` uncompressed bytes
/// (through a zip64 extra field) for a member that holds `data`.
fn zip_claiming(name: &str, data: &[u8], claimed: u64) -> Vec<u8> {
    let crc = crc32(data);
    let n = data.len() as u32;
    let mut z = Vec::new();
    // Local header: the true sizes.
    z.extend(0x0403_4b50u32.to_le_bytes());
    z.extend(45u16.to_le_bytes()); // version needed
    z.extend(0u16.to_le_bytes()); // flags
    z.extend(0u16.to_le_bytes()); // stored
    z.extend(0u16.to_le_bytes()); // time
    z.extend(0x21u16.to_le_bytes()); // date 1980-01-01
    z.extend(crc.to_le_bytes());
    z.extend(n.to_le_bytes());
    z.extend(n.to_le_bytes());
    z.extend((name.len() as u16).to_le_bytes());
    z.extend(0u16.to_le_bytes());
    z.extend(name.as_bytes());
    z.extend(data);
    let cd_start = z.len() as u32;
    // Central directory: uncompressed size 0xFFFFFFFF, the claim in the zip64 extra.
    z.extend(0x0201_4b50u32.to_le_bytes());
    z.extend(45u16.to_le_bytes()); // made by
    z.extend(45u16.to_le_bytes()); // needed
    z.extend(0u16.to_le_bytes());
    z.extend(0u16.to_le_bytes());
    z.extend(0u16.to_le_bytes());
    z.extend(0x21u16.to_le_bytes());
    z.extend(crc.to_le_bytes());
    z.extend(n.to_le_bytes());
    z.extend(0xFFFF_FFFFu32.to_le_bytes());
    z.extend((name.len() as u16).to_le_bytes());
    z.extend(12u16.to_le_bytes()); // extra length
    z.extend(0u16.to_le_bytes()); // comment
    z.extend(0u16.to_le_bytes()); // disk
    z.extend(0u16.to_le_bytes()); // internal attributes
    z.extend(0u32.to_le_bytes()); // external attributes
    z.extend(0u32.to_le_bytes()); // local header offset
    z.extend(name.as_bytes());
    z.extend(1u16.to_le_bytes()); // zip64 extra
    z.extend(8u16.to_le_bytes());
    z.extend(claimed.to_le_bytes());
    let cd_len = z.len() as u32 - cd_start;
    z.extend(0x0605_4b50u32.to_le_bytes());
    z.extend(0u16.to_le_bytes());
    z.extend(0u16.to_le_bytes());
    z.extend(1u16.to_le_bytes());
    z.extend(1u16.to_le_bytes());
    z.extend(cd_len.to_le_bytes());
    z.extend(cd_start.to_le_bytes());
    z.extend(0u16.to_le_bytes());
    z
}

fn verts_npy() -> (NpyArray, Vec<u8>) {
    let a = NpyArray::from_f32(vec![1220, 3], (0..3660).map(|i| i as f32).collect()).unwrap();
    let mut b = Vec::new();
    arkit_core::write_npy(&mut b, &a).unwrap();
    (a, b)
}

/// A v1.0 `.npy` header (aligned as numpy aligns it) for `shape_text` float32.
fn header_only(shape_text: &str) -> Vec<u8> {
    header_of("<f4", shape_text)
}

fn header_of(descr: &str, shape_text: &str) -> Vec<u8> {
    let mut h = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape_text}, }}");
    while !(10 + h.len() + 1).is_multiple_of(64) {
        h.push(' ');
    }
    h.push('\n');
    let mut b = b"\x93NUMPY\x01\x00".to_vec();
    b.extend((h.len() as u16).to_le_bytes());
    b.extend(h.as_bytes());
    b
}

fn zip_members(members: &[(String, Vec<u8>)], deflate: bool) -> Vec<u8> {
    let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let method = if deflate {
        zip::CompressionMethod::Deflated
    } else {
        zip::CompressionMethod::Stored
    };
    let options = zip::write::SimpleFileOptions::default().compression_method(method);
    for (name, bytes) in members {
        zip.start_file(name.as_str(), options).unwrap();
        zip.write_all(bytes).unwrap();
    }
    zip.finish().unwrap().into_inner()
}

#[test]
fn case1_a_member_claiming_100_gb_is_read_as_it_is() {
    let _turn = one_at_a_time();
    let (a, bytes) = verts_npy();
    let z = zip_claiming("verts.npy", &bytes, 100_000_000_000);
    let (res, peak) = peak_during(|| arkit_core::parse_npz(&z, Path::new("claim.npz")));
    // numpy reads the actual data; so do we, without reserving the claimed size.
    assert_eq!(res.unwrap().get("verts"), Some(&a));
    assert!(peak < 4 * MIB, "peak {peak} bytes");
}

#[test]
fn case2_a_deflate_bomb_is_refused_from_its_header_before_inflating() {
    let _turn = one_at_a_time();
    // A header declaring 2^30 float32 (4 GiB), then 8 MiB of zeros (deflated to ~8 KB).
    let mut member = header_only("(1073741824,)");
    member.resize(member.len() + 8 * MIB, 0);
    let z = zip_members(&[("verts.npy".into(), member)], true);
    assert!(z.len() < MIB / 4, "the bomb is small: {} bytes", z.len());
    let (res, peak) = peak_during(|| arkit_core::parse_npz(&z, Path::new("bomb.npz")));
    let e = res.unwrap_err().to_string();
    assert!(
        e.starts_with("bomb.npz:verts.npy: header says 1073741824 <f4 = 4294967296 bytes")
            && e.contains(&format!(
                "more than the {} bytes allowed",
                limits::MAX_ARRAY_BYTES
            )),
        "{e}"
    );
    assert!(peak < 2 * MIB, "peak {peak} bytes");
    // The same member, declaring a size within the limit but holding less, is read only
    // as far as it goes and reported truncated.
    let mut member = header_only("(4194304,)");
    member.resize(member.len() + MIB, 0);
    let z = zip_members(&[("verts.npy".into(), member)], true);
    let (res, peak) = peak_during(|| arkit_core::parse_npz(&z, Path::new("short.npz")));
    let e = res.unwrap_err().to_string();
    assert!(
        e.contains("truncated") && e.contains("file holds 1048576"),
        "{e}"
    );
    assert!(peak < 4 * MIB, "peak {peak} bytes");
}

#[test]
fn case2_members_add_up_to_the_archive_limit() {
    let _turn = one_at_a_time();
    // A deflated member of 200 MiB (uint8 zeros, decoded without a copy) is read; a
    // second declaring 100 MiB passes the per-array limit but not the archive's total.
    let mut first = header_of("|u1", &format!("({},)", 200 * MIB));
    first.resize(first.len() + 200 * MIB, 0);
    let second = header_of("|u1", &format!("({},)", 100 * MIB));
    let z = zip_members(&[("a.npy".into(), first), ("b.npy".into(), second)], true);
    let (res, peak) = peak_during(|| arkit_core::parse_npz(&z, Path::new("two.npz")));
    let e = res.unwrap_err().to_string();
    assert!(
        e.starts_with("two.npz:b.npy:") && e.contains("for the rest of the archive"),
        "{e}"
    );
    assert!(peak < 256 * MIB, "peak {peak} bytes");
}

#[test]
fn case3_trailing_bytes_are_bounded() {
    let _turn = one_at_a_time();
    let (a, bytes) = verts_npy();
    let mut ok = bytes.clone();
    ok.resize(bytes.len() + limits::MAX_NPY_TRAILING_BYTES as usize, 7);
    assert_eq!(arkit_core::parse_npy(&ok, Path::new("t.npy")).unwrap(), a);
    let mut bad = ok.clone();
    bad.push(7);
    let e = arkit_core::parse_npy(&bad, Path::new("t.npy"))
        .unwrap_err()
        .to_string();
    assert!(
        e.starts_with("t.npy:") && e.contains("after the array's data"),
        "{e}"
    );
    // In an archive, the tail is read through a cap, not inflated whole: 64 MiB of
    // deflated zeros after the data.
    let mut member = bytes.clone();
    member.resize(bytes.len() + 64 * MIB, 0);
    let z = zip_members(&[("verts.npy".into(), member)], true);
    let (res, peak) = peak_during(|| arkit_core::parse_npz(&z, Path::new("tail.npz")));
    let e = res.unwrap_err().to_string();
    assert!(
        e.starts_with("tail.npz:verts.npy:") && e.contains("after the array"),
        "{e}"
    );
    assert!(peak < 2 * MIB, "peak {peak} bytes");
    // A bare .npy with 4 GB after a valid array: refused from its length (a sparse file).
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("tail.npy");
    std::fs::write(&p, &bytes).unwrap();
    let f = std::fs::OpenOptions::new().write(true).open(&p).unwrap();
    f.set_len(4 << 30).unwrap();
    let (res, peak) = peak_during(|| arkit_core::read_npy(&p));
    let e = res.unwrap_err().to_string();
    assert!(
        e.contains("tail.npy: file is 4294967296 bytes, more than"),
        "{e}"
    );
    assert!(peak < MIB, "peak {peak} bytes");
    // Within the file limit, the stream stops after the allowance.
    f.set_len(bytes.len() as u64 + 10 * MIB as u64).unwrap();
    let (res, peak) = peak_during(|| arkit_core::read_npy(&p));
    assert!(
        res.unwrap_err()
            .to_string()
            .contains("after the array's data")
    );
    assert!(peak < MIB, "peak {peak} bytes");
}

#[test]
fn case4_npz_files_are_capped_before_reading() {
    let _turn = one_at_a_time();
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("huge_info.npz");
    let f = std::fs::File::create(&p).unwrap();
    f.set_len(limits::MAX_NPZ_FILE_BYTES + 1).unwrap();
    let (res, peak) = peak_during(|| arkit_core::read_npz(&p));
    let e = res.unwrap_err().to_string();
    assert!(
        e.contains("huge_info.npz: file is") && e.contains("allowed for an .npz file"),
        "{e}"
    );
    assert!(peak < MIB, "peak {peak} bytes");
    // A real-sized file reads.
    let (a, _) = verts_npy();
    let mut cur = std::io::Cursor::new(Vec::new());
    arkit_core::write_npz(&mut cur, &[("verts", &a)], NpzCompression::Stored).unwrap();
    std::fs::write(&p, cur.get_ref()).unwrap();
    assert_eq!(arkit_core::read_npz(&p).unwrap().get("verts"), Some(&a));
}

#[test]
fn case5_header_length_is_capped() {
    let _turn = one_at_a_time();
    let mut b = b"\x93NUMPY\x02\x00".to_vec();
    b.extend(0xFFFF_FFF0u32.to_le_bytes());
    let (res, peak) = peak_during(|| arkit_core::parse_npy(&b, Path::new("h.npy")));
    let e = res.unwrap_err().to_string();
    assert!(
        e.starts_with("h.npy: header length 4294967280 is more than"),
        "{e}"
    );
    assert!(peak < 64 * 1024, "peak {peak} bytes");
    // Exactly at the limit is allowed (and then parsed as any header).
    let mut h = "{'descr': '<f4', 'fortran_order': False, 'shape': (0,), }".to_string();
    h.push_str(&" ".repeat(limits::MAX_NPY_HEADER_BYTES - h.len() - 1));
    h.push('\n');
    let mut b = b"\x93NUMPY\x02\x00".to_vec();
    b.extend((h.len() as u32).to_le_bytes());
    b.extend(h.as_bytes());
    assert_eq!(
        arkit_core::parse_npy(&b, Path::new("h.npy")).unwrap().len(),
        0
    );
    let mut over = b"\x93NUMPY\x02\x00".to_vec();
    over.extend((h.len() as u32 + 1).to_le_bytes());
    over.extend(h.as_bytes());
    over.push(b'\n');
    assert!(arkit_core::parse_npy(&over, Path::new("h.npy")).is_err());
}

#[test]
fn case6_member_count_is_capped() {
    let _turn = one_at_a_time();
    let small = {
        let a = NpyArray::from_f64(vec![1], vec![1.0]).unwrap();
        let mut b = Vec::new();
        arkit_core::write_npy(&mut b, &a).unwrap();
        b
    };
    let members: Vec<(String, Vec<u8>)> = (0..=limits::MAX_NPZ_MEMBERS)
        .map(|i| (format!("m{i}.npy"), small.clone()))
        .collect();
    let z = zip_members(&members, false);
    let e = arkit_core::parse_npz(&z, Path::new("many.npz"))
        .unwrap_err()
        .to_string();
    assert_eq!(
        e,
        format!(
            "many.npz: {} members, more than the {} allowed",
            limits::MAX_NPZ_MEMBERS + 1,
            limits::MAX_NPZ_MEMBERS
        )
    );
    let z = zip_members(&members[..limits::MAX_NPZ_MEMBERS], false);
    assert_eq!(
        arkit_core::parse_npz(&z, Path::new("ok.npz"))
            .unwrap()
            .keys()
            .count(),
        limits::MAX_NPZ_MEMBERS
    );
}

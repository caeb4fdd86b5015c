//! The replay of a seed corpus and the seeded mutation loop, shared by the tests of
//! every crate's fuzz entries (`arkit_data::fuzz_entry`, `arkit_perspnet::fuzz_entry`).

use std::path::{Path, PathBuf};

/// An entry: arbitrary bytes in, whether they were accepted out.
pub type Entry = fn(&[u8]) -> bool;

/// The committed corpus (`fuzz/corpus`) of the workspace whose crate folder is
/// `manifest_dir` (a crate's `CARGO_MANIFEST_DIR`).
pub fn corpus_root(manifest_dir: &str) -> PathBuf {
    Path::new(manifest_dir).join("../../fuzz/corpus")
}

/// The seeds of `target`, sorted by name.
pub fn seeds(corpus: &Path, target: &str) -> Vec<(PathBuf, Vec<u8>)> {
    let dir = corpus.join(target);
    let entries = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("seed corpus {} missing: {e}", dir.display()));
    let mut files: Vec<PathBuf> = entries
        .map(|e| e.expect("directory entry").path())
        .filter(|p| p.is_file())
        .collect();
    files.sort();
    files
        .into_iter()
        .map(|p| {
            let b = std::fs::read(&p).expect("read seed");
            (p, b)
        })
        .collect()
}

/// Replays the seeds of `target` (in `corpus`) through `entry`: at least `min_files`,
/// none panicking, at least `min_accepted` accepted; returns those accepted.
pub fn replay(
    corpus: &Path,
    target: &str,
    entry: Entry,
    min_files: usize,
    min_accepted: usize,
) -> Vec<Vec<u8>> {
    let files = seeds(corpus, target);
    assert!(
        files.len() >= min_files,
        "{target}: {} seed files, expected at least {min_files}",
        files.len()
    );
    let mut accepted = Vec::new();
    for (f, bytes) in &files {
        let ok = std::panic::catch_unwind(|| entry(bytes))
            .unwrap_or_else(|_| panic!("{target}: {} panicked", f.display()));
        if ok {
            accepted.push(bytes.clone());
        }
    }
    assert!(
        accepted.len() >= min_accepted,
        "{target}: {} of {} seeds accepted, expected at least {min_accepted}",
        accepted.len(),
        files.len()
    );
    accepted
}

/// Checks that the seeds of `target` (in `corpus`) whose names contain one of `damaged`
/// and none of `but` are refused by `entry`: the checks that refuse them (lengths,
/// CRCs, bounds) are in place. At least one seed must be so named.
pub fn refused(corpus: &Path, target: &str, entry: Entry, damaged: &[&str], but: &[&str]) {
    let mut n = 0;
    for (path, bytes) in seeds(corpus, target) {
        let name = path
            .file_name()
            .expect("a file")
            .to_string_lossy()
            .into_owned();
        if damaged.iter().any(|d| name.contains(d)) && !but.iter().any(|b| name.contains(b)) {
            assert!(
                !entry(&bytes),
                "{target}: the damaged seed {name} was accepted"
            );
            n += 1;
        }
    }
    assert!(n > 0, "{target}: no damaged seeds");
}

/// A small deterministic generator (xorshift64*), so that a failing mutation is
/// reproduced from its seed.
pub struct Rng(pub u64);

impl Rng {
    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }

    /// A number below `n` (0 when `n` is 0).
    pub fn below(&mut self, n: usize) -> usize {
        (self.next_u64() % n.max(1) as u64) as usize
    }
}

/// `input` mutated once or a few times: bits flipped, bytes set to edge values, a
/// 32-bit field set to an edge value (0, 1, a power of two, all ones, the input's
/// length), a piece cut, repeated or spliced from `other`, the input truncated.
pub fn mutate(rng: &mut Rng, input: &[u8], other: &[u8]) -> Vec<u8> {
    let mut v = input.to_vec();
    for _ in 0..1 + rng.below(4) {
        let len = v.len();
        match rng.below(8) {
            0 if len > 0 => {
                let i = rng.below(len);
                v[i] ^= 1 << rng.below(8);
            }
            1 if len > 0 => {
                let i = rng.below(len);
                v[i] = [0, 1, 0x7f, 0x80, 0xff][rng.below(5)];
            }
            2 if len >= 4 => {
                let i = rng.below(len - 3);
                let x: u32 = match rng.below(6) {
                    0 => 0,
                    1 => 1,
                    2 => 1 << rng.below(32),
                    3 => u32::MAX,
                    4 => len as u32,
                    _ => u32::from_le_bytes(v[i..i + 4].try_into().unwrap()).wrapping_add(1),
                };
                v[i..i + 4].copy_from_slice(&x.to_le_bytes());
            }
            3 if len > 0 => {
                let a = rng.below(len);
                let b = (a + 1 + rng.below(64)).min(len);
                v.drain(a..b);
            }
            4 if len > 0 => {
                let a = rng.below(len);
                let b = (a + 1 + rng.below(64)).min(len);
                let piece = v[a..b].to_vec();
                let at = rng.below(len);
                v.splice(at..at, piece);
            }
            5 if !other.is_empty() => {
                let a = rng.below(other.len());
                let b = (a + 1 + rng.below(256)).min(other.len());
                let at = rng.below(len + 1);
                let end = (at + (b - a)).min(len);
                v.splice(at..end, other[a..b].iter().copied());
            }
            6 => v.truncate(rng.below(len + 1)),
            _ if len > 0 => {
                // A digit or a JSON token changed, for the text formats.
                let i = rng.below(len);
                v[i] = b"0123456789-.e\"{}[],:null"[rng.below(24)];
            }
            _ => {}
        }
    }
    v
}

/// Runs `iters` mutations of `target`'s seeds through `entry`; returns the count run and
/// accepted. For `crop_part`, half the inputs are resealed (flag bit 0) so the
/// mutations reach past the CRCs.
pub fn mutation_run(
    corpus: &Path,
    target: &str,
    entry: Entry,
    iters: usize,
    seed: u64,
) -> (usize, usize) {
    let corpus: Vec<Vec<u8>> = seeds(corpus, target).into_iter().map(|(_, b)| b).collect();
    assert!(!corpus.is_empty(), "{target}: no seeds");
    let mut rng = Rng(seed | 1);
    let mut accepted = 0;
    for i in 0..iters {
        let a = &corpus[rng.below(corpus.len())];
        let b = &corpus[rng.below(corpus.len())];
        let mut m = mutate(&mut rng, a, b);
        if target == "crop_part" && rng.below(2) == 0 {
            // Mutate the part alone and reseal it, keeping the manifest and keys whole.
            if let Some(p) = super::container::split(a, 4) {
                let part = mutate(&mut rng, p[3], b);
                let flags = [&[p[2][0] | 1][..], &p[2][1..]].concat();
                m = super::container::join(&[p[0], p[1], &flags, &part]);
            }
        }
        let ok = std::panic::catch_unwind(|| entry(&m)).unwrap_or_else(|_| {
            let out = std::env::temp_dir().join(format!("arkit-fuzz-crash-{target}-{i}"));
            std::fs::write(&out, &m).unwrap();
            panic!(
                "{target}: mutation {i} (seed {seed}) panicked; input kept in {}",
                out.display()
            )
        });
        accepted += ok as usize;
    }
    (iters, accepted)
}

/// The mutation loop of [`mutation_run`] over `targets`, `ARKIT_FUZZ_ITERS` inputs each
/// (`default` when unset) from seed `ARKIT_FUZZ_SEED` (53 when unset); prints each
/// target's count, accepted inputs and time.
pub fn mutation_loop(corpus: &Path, targets: &[(&str, Entry)], default: usize) {
    let var = |name: &str| std::env::var(name).ok().and_then(|v| v.parse::<u64>().ok());
    let iters = var("ARKIT_FUZZ_ITERS").map_or(default, |v| v as usize);
    let seed = var("ARKIT_FUZZ_SEED").unwrap_or(53);
    for &(name, entry) in targets {
        let t = std::time::Instant::now();
        let (n, ok) = mutation_run(corpus, name, entry, iters, seed);
        eprintln!(
            "fuzz {name}: {n} mutated inputs, {ok} accepted, {:.1} s",
            t.elapsed().as_secs_f64()
        );
    }
}

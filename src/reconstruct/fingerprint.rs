//! What a run was made from: a hash of each input of the scan (scan.toml, each calibration
//! file, the decoded data of the views used) and the list of views, kept in the checkpoint, so
//! that `--resume` against another scan, or the same scan decoded again, is refused with what
//! changed instead of mixing two scans' data in one result.

use std::collections::BTreeMap;
use std::io::Read;
use std::path::Path;

use anyhow::{Context, Result};

use crate::scan::decoded::is_view_file;
use crate::scan::Scan;

/// Input name → hash (16 hex digits).
pub type Fingerprint = BTreeMap<String, String>;

/// The fingerprint of `scan`'s inputs for a run over `views`.
pub fn of_scan(scan: &Scan, views: &[usize]) -> Result<Fingerprint> {
    let c = &scan.config.calibration;
    let mut f = Fingerprint::new();
    let files = [
        ("scan.toml", Some(Path::new("scan.toml"))),
        ("camera", Some(c.camera.as_path())),
        ("screen", Some(c.screen.as_path())),
        ("turntable", Some(c.turntable.as_path())),
        ("poses", c.poses.as_deref()),
    ];
    for (name, file) in files {
        if let Some(file) = file {
            let mut h = Hasher::new();
            h.file(&scan.dir.join(file))?;
            f.insert(name.into(), h.hex());
        }
    }
    f.insert(
        "decoded".into(),
        decoded_hash(&scan.dir.join("decoded"), views)?,
    );
    f.insert("views".into(), format!("{views:?}"));
    Ok(f)
}

/// What differs between the fingerprint a run was made from and the current one, as a list of
/// input names; empty when they agree.
pub fn changes(was: &Fingerprint, now: &Fingerprint) -> Vec<String> {
    let names: std::collections::BTreeSet<&String> = was.keys().chain(now.keys()).collect();
    names
        .into_iter()
        .filter(|n| was.get(*n) != now.get(*n))
        .cloned()
        .collect()
}

/// The hash of `decoded/summary.json` and every file of the views used, in name order.
fn decoded_hash(dir: &Path, views: &[usize]) -> Result<String> {
    let mut h = Hasher::new();
    h.file(&dir.join("summary.json"))?;
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .with_context(|| format!("cannot read {}", dir.display()))?
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| views.iter().any(|&k| is_view_file(n, k)))
        .collect();
    names.sort();
    for n in names {
        h.bytes(n.as_bytes());
        h.file(&dir.join(n))?;
    }
    Ok(h.hex())
}

/// FNV-1a over 64-bit words (a stable hash: the same bytes give the same value with any build).
struct Hasher(u64);

impl Hasher {
    const PRIME: u64 = 0x0000_0100_0000_01b3;

    fn new() -> Self {
        Self(0xcbf2_9ce4_8422_2325)
    }

    fn bytes(&mut self, b: &[u8]) {
        let mut chunks = b.chunks_exact(8);
        for c in &mut chunks {
            let w = u64::from_le_bytes(c.try_into().expect("8 bytes"));
            self.0 = (self.0 ^ w).wrapping_mul(Self::PRIME);
        }
        for &r in chunks.remainder() {
            self.0 = (self.0 ^ u64::from(r)).wrapping_mul(Self::PRIME);
        }
        self.0 = (self.0 ^ b.len() as u64).wrapping_mul(Self::PRIME);
    }

    fn file(&mut self, path: &Path) -> Result<()> {
        let mut f =
            std::fs::File::open(path).with_context(|| format!("cannot read {}", path.display()))?;
        let mut buf = vec![0u8; 1 << 20];
        loop {
            let n = f
                .read(&mut buf)
                .with_context(|| format!("cannot read {}", path.display()))?;
            if n == 0 {
                return Ok(());
            }
            self.bytes(&buf[..n]);
        }
    }

    fn hex(&self) -> String {
        format!("{:016x}", self.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn changes_name_what_differs() {
        let a: Fingerprint = [("camera", "1"), ("decoded", "2")]
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .into();
        let mut b = a.clone();
        assert!(changes(&a, &b).is_empty());
        b.insert("decoded".into(), "3".into());
        b.insert("poses".into(), "4".into());
        assert_eq!(changes(&a, &b), ["decoded", "poses"]);
    }

    #[test]
    fn the_hash_sees_every_byte_and_the_length() {
        let h = |b: &[u8]| {
            let mut h = Hasher::new();
            h.bytes(b);
            h.0
        };
        assert_ne!(h(b"abcdefgh1"), h(b"abcdefgh2"));
        assert_ne!(h(b"abcdefgh"), h(b"bbcdefgh"));
        assert_ne!(h(b""), h(b"\0"));
    }
}

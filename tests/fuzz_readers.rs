//! Property-based fuzzing of every reader of user files: valid files mutated at random (bytes
//! flipped, truncated, hostile numbers and brackets spliced in) must give an error or a value,
//! never a panic, an abort or an allocation beyond the memory budget (1 GiB here).
//!
//! Seeded and bounded: `GLASSCAN_FUZZ_CASES` cases per reader (default 64, as `make test`
//! runs them; `make fuzz` runs 100,000).

use std::path::{Path, PathBuf};

use glasscan::import::drt::import_drt;
use glasscan::mesh::io::{read_mesh, write_mesh, write_mesh_as, MeshFormat};
use glasscan::mesh::shapes::icosphere;
use glasscan::reconstruct::config::{Preset, Settings};
use glasscan::rig::calib_io::{read_view_poses, write_view_poses};
use glasscan::scan::decoded::{read_rays, DecodedScan};
use glasscan::scan::Scan;
use glasscan::simulate::{simulate, SimulateOptions};
use nalgebra::Isometry3;
use proptest::prelude::*;
use proptest::test_runner::{Config, RngSeed, TestRunner};

/// Text spliced into files: numbers at and past every limit, broken structure.
const TOKENS: &[&str] = &[
    "-1",
    "0",
    "1e308",
    "-1e308",
    "nan",
    "inf",
    "-inf",
    "99999999999999999999",
    "4294967296",
    "18446744073709551615",
    "-0",
    "1e-300",
    "\"abc\"",
    "[",
    "]",
    "{",
    "}",
    ":",
    ",",
    "\n",
    "#",
    "rows: 100000",
    "data: [",
    "element vertex 4294967295\n",
    "property list uint uint vertex_indices\n",
    "f 1 2 99999999\n",
    "v nan 0 0\n",
    "= [",
    "stages = 0",
    "\0",
    "\u{feff}",
    "%YAML:1.0\n",
];

/// One edit of a file: (position, byte, token index, kind).
type Edit = (usize, u8, usize, u8);

fn edits() -> impl Strategy<Value = Vec<Edit>> {
    prop::collection::vec(
        (0usize..1 << 20, any::<u8>(), 0..TOKENS.len(), 0u8..8),
        1..4,
    )
}

/// Applies `edits` to `bytes`: flip a byte, truncate, splice a token in, replace a run of digits
/// with a token, or (half of the edits) change a digit into another, which keeps most files
/// readable with other values.
fn mutate(bytes: &[u8], edits: &[Edit]) -> Vec<u8> {
    let mut b = bytes.to_vec();
    for &(pos, byte, token, kind) in edits {
        let i = if b.is_empty() { 0 } else { pos % b.len() };
        let t = TOKENS[token].as_bytes();
        match kind {
            0 if !b.is_empty() => b[i] = byte,
            1 => b.truncate(i),
            2 => {
                b.splice(i..i, t.iter().copied());
            }
            4..=7 => {
                if let Some(j) = (i..b.len()).find(|&j| b[j].is_ascii_digit()) {
                    b[j] = b'0' + byte % 10;
                }
            }
            _ => {
                let end = (i..b.len())
                    .find(|&j| !b[j].is_ascii_digit() && b[j] != b'.')
                    .unwrap_or(b.len());
                b.splice(i..end, t.iter().copied());
            }
        }
    }
    b
}

fn runner() -> TestRunner {
    glasscan::util::budget::set_limit_gb(1.0).unwrap();
    let cases = std::env::var("GLASSCAN_FUZZ_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(64);
    TestRunner::new(Config {
        cases,
        rng_seed: RngSeed::Fixed(20261123),
        failure_persistence: None,
        max_shrink_iters: 200,
        ..Config::default()
    })
}

/// Runs `read` on mutations of `sample` written to a file named `name`; returns how many of
/// them read without error and how many were refused (both must happen, or the fuzzing tests
/// nothing).
fn fuzz(name: &str, sample: &[u8], read: impl Fn(&Path) -> bool) -> (usize, usize) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join(name);
    let counts = std::cell::Cell::new((0, 0));
    runner()
        .run(&edits(), |e| {
            std::fs::write(&path, mutate(sample, &e)).unwrap();
            let (ok, refused) = counts.get();
            counts.set(if read(&path) {
                (ok + 1, refused)
            } else {
                (ok, refused + 1)
            });
            Ok(())
        })
        .unwrap();
    let (ok, refused) = counts.get();
    eprintln!("{name}: {ok} mutated files read, {refused} refused");
    assert!(refused > 0, "{name}: no mutation was refused");
    (ok, refused)
}

/// A tiny decoded scan (2 views, 32×24) in a fresh temporary folder, and its path.
fn scan() -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("scan");
    let o = SimulateOptions {
        views: 2,
        width: 32,
        height: 24,
        spp: 1,
        decoded_only: true,
        ..Default::default()
    };
    simulate(&icosphere(25.0, 2), &path, &o, |_| ()).unwrap();
    (dir, path)
}

/// Copies the text files and decoded data of the scan `from` into `to`.
fn copy_scan(from: &Path, to: &Path) {
    std::fs::create_dir_all(to.join("decoded")).unwrap();
    for sub in ["", "decoded"] {
        for e in std::fs::read_dir(from.join(sub)).unwrap() {
            let p = e.unwrap().path();
            if p.is_file() {
                std::fs::copy(&p, to.join(sub).join(p.file_name().unwrap())).unwrap();
            }
        }
    }
}

#[test]
fn mesh_readers_survive_mutated_files() {
    let mesh = icosphere(10.0, 1);
    let dir = tempfile::tempdir().unwrap();
    for (name, format) in [
        ("m.ply", MeshFormat::PlyAscii),
        ("b.ply", MeshFormat::PlyBinary),
        ("m.obj", MeshFormat::Obj),
    ] {
        let p = dir.path().join(name);
        write_mesh_as(&p, &mesh, format).unwrap();
        let sample = std::fs::read(&p).unwrap();
        let (ok, _) = fuzz(name, &sample, |path| read_mesh(path).is_ok());
        assert!(ok > 0, "{name}: every mutation was refused");
    }
}

#[test]
fn scan_and_calibration_readers_survive_mutated_files() {
    let (_scan_dir, from) = scan();
    for name in ["scan.toml", "camera.yml", "screen.yml", "turntable.yml"] {
        let dir = tempfile::tempdir().unwrap();
        let to = dir.path().join("s");
        copy_scan(&from, &to);
        let sample = std::fs::read(to.join(name)).unwrap();
        runner()
            .run(&edits(), |e| {
                std::fs::write(to.join(name), mutate(&sample, &e)).unwrap();
                if let Ok(scan) = Scan::open(&to) {
                    let _ = scan.view_poses();
                }
                Ok(())
            })
            .unwrap();
    }
    let dir = tempfile::tempdir().unwrap();
    let poses = dir.path().join("poses.yml");
    write_view_poses(&poses, &[Isometry3::identity(); 3]).unwrap();
    fuzz("poses.yml", &std::fs::read(&poses).unwrap(), |p| {
        read_view_poses(p).is_ok()
    });
}

#[test]
fn config_reader_survives_mutated_files() {
    let sample = b"stages = 3\nstart_edge = 0.1\nrobust = { huber = 1.0 }\n\
        optimizer = { large_steps = { lambda = 20.0, lr_edge = 0.3, beta1 = 0.9, beta2 = 0.999 } }\n\
        smoothness = { tolerant = { tau = 0.5 } }\nmax_refractions = 2\n";
    let (ok, _) = fuzz("c.toml", sample, |p| {
        let text = String::from_utf8_lossy(&std::fs::read(p).unwrap()).into_owned();
        match Settings::preset(Preset::Fast).with_overrides(&text) {
            Ok(s) if s.check().is_ok() => s.edge_mm(s.stages - 1, 100.0).is_finite(),
            _ => false,
        }
    });
    assert!(ok > 0, "every mutated config was refused");
}

#[test]
fn decoded_form_readers_survive_mutated_files() {
    let (_scan_dir, from) = scan();
    let scan = Scan::open(&from).unwrap();
    let size = (scan.camera.width, scan.camera.height);
    for name in ["summary.json", "view_000_mask.png", "view_000_monitor.png"] {
        let dir = tempfile::tempdir().unwrap();
        let to = dir.path().join("s");
        copy_scan(&from, &to);
        let sample = std::fs::read(to.join("decoded").join(name)).unwrap();
        runner()
            .run(&edits(), |e| {
                std::fs::write(to.join("decoded").join(name), mutate(&sample, &e)).unwrap();
                if let Ok(d) = DecodedScan::open(&to, size) {
                    let _ = d.view(0);
                }
                Ok(())
            })
            .unwrap();
    }
    // A rays file, as import-drt writes them.
    let mut sample = b"GSRAYS01".to_vec();
    sample.extend_from_slice(&2u64.to_le_bytes());
    for pixel in [3u32, 7] {
        sample.extend_from_slice(&pixel.to_le_bytes());
        for v in [0.0f32, 0.0, 1.0, 5.0, 6.0, 700.0] {
            sample.extend_from_slice(&v.to_le_bytes());
        }
    }
    fuzz("view_000_rays.bin", &sample, |p| {
        read_rays(p, 32 * 24).is_ok()
    });
}

/// HDF5 files in DRT's layout whose datasets have hostile shapes and types (the bytes of an
/// HDF5 file are the HDF5 library's to check; the shapes and values are ours).
#[test]
fn drt_import_survives_hostile_shapes() {
    let dir = tempfile::tempdir().unwrap();
    let dims = prop::collection::vec(
        prop_oneof![Just(0usize), Just(1), Just(3), Just(4), Just(72), 0usize..9],
        0..5,
    );
    let strategy = (
        dims.clone(),
        dims.clone(),
        dims,
        any::<bool>(),
        -2.0f64..2.0,
    );
    let mut r = runner();
    r.run(&strategy, |(mask, pos, proj, big, value)| {
        let file = dir.path().join("f.h5");
        let f = hdf5::File::create(&file).unwrap();
        let make = |name: &str, shape: &[usize]| {
            let n: usize = shape.iter().product();
            let data = ndarray::ArrayD::from_shape_vec(shape.to_vec(), vec![value; n]).unwrap();
            f.new_dataset_builder()
                .with_data(&data)
                .create(name)
                .unwrap();
        };
        make("cam_proj", &proj);
        make("cam_k", &[3, 3]);
        if big {
            f.new_dataset::<u8>()
                .chunk((1, 64, 64))
                .shape((72, 50_000, 50_000))
                .create("mask")
                .unwrap();
        } else {
            make("mask", &mask);
        }
        make("screen_position", &pos);
        f.close().unwrap();
        let _ = import_drt(&file, &dir.path().join("out"), None, 1.5, true, |_| ());
        Ok(())
    })
    .unwrap();
}

#[test]
fn mutations_change_the_files() {
    let sample = b"ply\nformat ascii 1.0\nelement vertex 3\n";
    let e = [(5usize, b'x', 0usize, 0u8), (0, 0, 1, 2), (20, 0, 2, 3)];
    let m = mutate(sample, &e);
    assert_ne!(m, sample.to_vec());
    assert!(String::from_utf8_lossy(&m).contains("0"));
    // The helpers above must really write what they read back.
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("x.ply");
    write_mesh(&p, &icosphere(5.0, 0)).unwrap();
    assert!(read_mesh(&p).is_ok());
}

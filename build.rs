//! Builds the C shim over Embree (`wrapper/`) with CMake (`cmake/`), generates its Rust bindings
//! with bindgen, and links Embree. A missing tool or library stops the build with one line that
//! names the Debian package to install.

use std::path::{Path, PathBuf};
use std::process::Command;

/// Stops the build with a single, actionable line.
fn fail(msg: &str) -> ! {
    eprintln!("error: {msg}");
    println!("cargo:warning={msg}");
    std::process::exit(1);
}

fn embree_headers_present() -> bool {
    let mut roots: Vec<PathBuf> = vec!["/usr/include".into(), "/usr/local/include".into()];
    for var in ["EMBREE_DIR", "embree_DIR", "CMAKE_PREFIX_PATH"] {
        if let Ok(v) = std::env::var(var) {
            for p in std::env::split_paths(&v) {
                roots.push(p.join("include"));
                roots.push(p.clone());
            }
        }
    }
    roots
        .iter()
        .any(|r| r.join("embree3/rtcore.h").is_file() || r.join("embree4/rtcore.h").is_file())
}

fn main() {
    println!("cargo:rerun-if-changed=wrapper");
    println!("cargo:rerun-if-changed=cmake");
    for var in ["EMBREE_DIR", "embree_DIR", "CMAKE_PREFIX_PATH"] {
        println!("cargo:rerun-if-env-changed={var}");
    }

    if Command::new("cmake").arg("--version").output().is_err() {
        fail("glasscan: cmake not found; install it: apt-get install cmake");
    }
    if !embree_headers_present() {
        fail(
            "glasscan: Embree headers (embree3/rtcore.h or embree4/rtcore.h) not found; \
             install them: apt-get install libembree-dev (or set EMBREE_DIR)",
        );
    }

    let dst = cmake::Config::new("cmake").profile("Release").build();
    println!(
        "cargo:rustc-link-search=native={}",
        dst.join("lib").display()
    );
    println!("cargo:rustc-link-lib=static=glasscan_embree");

    let link_file = dst.join("embree_link.txt");
    let lib = std::fs::read_to_string(&link_file).unwrap_or_else(|e| {
        fail(&format!(
            "glasscan: cannot read {}: {e}",
            link_file.display()
        ))
    });
    let lib = Path::new(lib.trim());
    let dir = lib
        .parent()
        .unwrap_or_else(|| fail("glasscan: Embree library path has no folder"));
    let file = lib.file_name().and_then(|f| f.to_str()).unwrap_or_default();
    // libembree3.so.3.13.5 -> embree3
    let name = file
        .strip_prefix("lib")
        .and_then(|f| f.split(".so").next())
        .unwrap_or_else(|| {
            fail(&format!(
                "glasscan: unexpected Embree library name {}",
                lib.display()
            ))
        });
    println!("cargo:rustc-link-search=native={}", dir.display());
    println!("cargo:rustc-link-lib=dylib={name}");

    let bindings = bindgen::Builder::default()
        .header("wrapper/glasscan_embree.h")
        .allowlist_function("gs_.*")
        .allowlist_type("gs_.*")
        .allowlist_var("GS_.*")
        .rustified_enum("gs_build_mode")
        .derive_default(true)
        .generate()
        .unwrap_or_else(|e| {
            fail(&format!(
                "glasscan: bindgen failed ({e}); it needs libclang: apt-get install clang libclang-dev"
            ))
        });
    let out = PathBuf::from(std::env::var("OUT_DIR").expect("cargo sets OUT_DIR"));
    bindings
        .write_to_file(out.join("embree_ffi.rs"))
        .unwrap_or_else(|e| fail(&format!("glasscan: cannot write bindings: {e}")));
}

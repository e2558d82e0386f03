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

/// An Embree found without CMake: its header folder (holding `embree4/` or `embree3/`), its
/// shared library and major version.
struct ExplicitEmbree {
    include: PathBuf,
    library: PathBuf,
    major: u32,
}

/// The environment variables that point the build at an Embree.
const EMBREE_VARS: [&str; 5] = [
    "EMBREE4_INCLUDE_DIR",
    "EMBREE4_LIB_DIR",
    "EMBREE_DIR",
    "embree_DIR",
    "CMAKE_PREFIX_PATH",
];

/// The Embree named by `EMBREE4_INCLUDE_DIR` + `EMBREE4_LIB_DIR` (e.g. a release archive or a
/// library from a Python wheel), or by `EMBREE_DIR` holding `include/` and `lib/` (or `lib64/`)
/// without a CMake package config. `None`: let CMake search for a package config.
fn explicit_embree() -> Option<ExplicitEmbree> {
    let var = |k: &str| std::env::var_os(k).map(PathBuf::from);
    if let (Some(include), Some(lib)) = (var("EMBREE4_INCLUDE_DIR"), var("EMBREE4_LIB_DIR")) {
        if !include.join("embree4/rtcore.h").is_file() {
            fail(&format!(
                "glasscan: EMBREE4_INCLUDE_DIR={} has no embree4/rtcore.h",
                include.display()
            ));
        }
        let library = lib.join("libembree4.so");
        if !library.exists() {
            fail(&format!(
                "glasscan: EMBREE4_LIB_DIR={} has no libembree4.so",
                lib.display()
            ));
        }
        return Some(ExplicitEmbree {
            include,
            library,
            major: 4,
        });
    }
    let root = var("EMBREE_DIR")?;
    for major in [4, 3] {
        let include = root.join("include");
        if !include.join(format!("embree{major}/rtcore.h")).is_file() {
            continue;
        }
        for lib in ["lib", "lib64"] {
            let library = root.join(lib).join(format!("libembree{major}.so"));
            if library.exists() {
                return Some(ExplicitEmbree {
                    include,
                    library,
                    major,
                });
            }
        }
    }
    None
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

/// Builds the shim with CMake against `explicit` (or a package config) and returns the folder
/// it was installed to. The three variables are always defined, empty without `explicit`: CMake
/// keeps a variable from the build folder's previous configure when it is not given again, so a
/// build after `make test-embree4` would otherwise link Embree 4 without its rpath.
fn build_shim(explicit: Option<&ExplicitEmbree>) -> PathBuf {
    let mut config = cmake::Config::new("cmake");
    config.profile("Release");
    let (include, library, major) = match explicit {
        Some(e) => (e.include.clone(), e.library.clone(), e.major.to_string()),
        None => Default::default(),
    };
    config
        .define("GS_EMBREE_INCLUDE_DIR", include)
        .define("GS_EMBREE_LIBRARY", library)
        .define("GS_EMBREE_MAJOR", major);
    config.build()
}

/// The font of the plots' text: copied into OUT_DIR and compiled into the binary, so plots need
/// no font at run time. `GLASSCAN_FONT` names another TrueType file.
fn plot_font() {
    println!("cargo:rerun-if-env-changed=GLASSCAN_FONT");
    let candidates = [
        std::env::var("GLASSCAN_FONT").unwrap_or_default(),
        "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf".into(),
        "/usr/share/fonts/TTF/DejaVuSans.ttf".into(),
        "/usr/share/fonts/dejavu/DejaVuSans.ttf".into(),
    ];
    let Some(font) = candidates
        .iter()
        .find(|c| !c.is_empty() && Path::new(c).is_file())
    else {
        fail(
            "glasscan: the plots' font DejaVuSans.ttf not found; install it: apt-get install \
             fonts-dejavu-core (or set GLASSCAN_FONT to a .ttf file)",
        );
    };
    let out = PathBuf::from(std::env::var("OUT_DIR").expect("cargo sets OUT_DIR"));
    std::fs::copy(font, out.join("plot_font.ttf"))
        .unwrap_or_else(|e| fail(&format!("glasscan: cannot copy {font}: {e}")));
}

fn main() {
    plot_font();
    println!("cargo:rerun-if-changed=wrapper");
    println!("cargo:rerun-if-changed=cmake");
    for var in EMBREE_VARS {
        println!("cargo:rerun-if-env-changed={var}");
    }

    if Command::new("cmake").arg("--version").output().is_err() {
        fail("glasscan: cmake not found; install it: apt-get install cmake");
    }
    let explicit = explicit_embree();
    if explicit.is_none() && !embree_headers_present() {
        fail(
            "glasscan: Embree headers (embree3/rtcore.h or embree4/rtcore.h) not found; \
             install them: apt-get install libembree-dev (or set EMBREE_DIR, or \
             EMBREE4_INCLUDE_DIR and EMBREE4_LIB_DIR)",
        );
    }

    let dst = build_shim(explicit.as_ref());
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
    // An Embree outside the loader's default folders is found at run time through an rpath.
    if explicit.is_some() {
        println!("cargo:rustc-link-arg=-Wl,-rpath,{}", dir.display());
    }

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

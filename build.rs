//! Links libtorch_cuda eagerly and records where the repo's libtorch lives.
//!
//! Without `--no-as-needed` the linker drops `libtorch_cuda.so` (nothing references
//! it by symbol), and CUDA then silently reports as unavailable at run time.
use std::path::{Path, PathBuf};

fn torch_lib_dir() -> Option<PathBuf> {
    if let Ok(dir) = std::env::var("LIBTORCH_LIB") {
        return Some(PathBuf::from(dir));
    }
    if let Ok(dir) = std::env::var("LIBTORCH") {
        return Some(Path::new(&dir).join("lib"));
    }
    // The repo's own venv (scripts/dev installs torch==2.11.0 there).
    let root = PathBuf::from(std::env::var("CARGO_MANIFEST_DIR").ok()?);
    let lib = root.join(".venv/lib");
    for entry in std::fs::read_dir(lib).ok()?.flatten() {
        let candidate = entry.path().join("site-packages/torch/lib");
        if candidate.join("libtorch_cpu.so").exists() {
            return Some(candidate);
        }
    }
    None
}

fn compile_protos() {
    println!("cargo:rerun-if-changed=proto");
    // protoc comes from a crate, so a fresh machine needs no system protobuf compiler.
    let protoc = protoc_bin_vendored::protoc_bin_path().expect("vendored protoc");
    std::env::set_var("PROTOC", protoc);
    let out = PathBuf::from(std::env::var("OUT_DIR").expect("OUT_DIR"));
    tonic_prost_build::configure()
        .bytes(".")
        .file_descriptor_set_path(out.join("loopd_descriptor.bin"))
        .compile_protos(&["proto/loopd/v1/loopd.proto"], &["proto"])
        .expect("compiling proto/loopd/v1/loopd.proto");
}

fn main() {
    compile_protos();
    println!("cargo:rerun-if-env-changed=LIBTORCH_LIB");
    println!("cargo:rerun-if-env-changed=LIBTORCH");
    println!("cargo:rerun-if-changed=build.rs");
    let Some(lib) = torch_lib_dir() else { return };
    println!("cargo:rustc-link-search=native={}", lib.display());
    if lib.join("libtorch_cuda.so").exists() {
        println!("cargo:rustc-link-arg=-Wl,--no-as-needed");
        println!("cargo:rustc-link-arg=-ltorch_cuda");
        println!("cargo:rustc-link-arg=-Wl,--as-needed");
    }
    // Runs from the build tree without LD_LIBRARY_PATH; on other machines
    // (the GPU hosts) LD_LIBRARY_PATH takes precedence over this RUNPATH.
    println!("cargo:rustc-link-arg=-Wl,-rpath,{}", lib.display());
}

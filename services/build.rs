//! With the `realsense` feature: librealsense carries its own LZ4 (its `.bag`
//! recordings are LZ4-compressed), and so does the camera through rerun (mcap's
//! lz4-sys), a newer one. An executable exports every symbol a shared library
//! it links also defines, and the dynamic linker then binds librealsense's own
//! LZ4 calls to the executable's: a recording no longer reads ("Config cannot be
//! resolved"). The camera's symbols from static libraries stay hidden instead.
fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    if std::env::var_os("CARGO_FEATURE_REALSENSE").is_some() {
        println!("cargo:rustc-link-arg-bin=camera=-Wl,--exclude-libs,ALL");
    }
}

//! The VDB import path: any bytes must give a grid or an error, never a crash.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(imp) = modeler::vdb::read_vdb_bytes(data, "fuzz.vdb", None) {
        assert!(imp.grid.max_value().is_finite());
    }
});

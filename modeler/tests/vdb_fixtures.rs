//! The VDB fixtures in tests/data/vdb are what their script makes: make_fixtures.py,
//! run into a temporary directory with Debian's python3-openvdb, must write the same
//! JSON truth and the same .vdb bytes as the committed ones (the script fixes
//! OpenVDB's random header UUID, so the output is deterministic). CI installs
//! python3-openvdb; elsewhere the test is skipped with a message if it is missing.

use serde_json::Value;
use std::path::Path;
use std::process::Command;

const FIXTURES: [&str; 7] =
    ["sphere_dense", "cloud_sparse", "transformed_zip", "multi_grid", "half_float", "half_zip", "half_sparse"];

/// The first place where two JSON values differ, as a path and the two values.
fn first_difference(a: &Value, b: &Value, at: &str) -> Option<String> {
    match (a, b) {
        (Value::Object(x), Value::Object(y)) => {
            if x.keys().ne(y.keys()) {
                return Some(format!(
                    "{at}: keys {:?} vs {:?}",
                    x.keys().collect::<Vec<_>>(),
                    y.keys().collect::<Vec<_>>()
                ));
            }
            x.iter().find_map(|(k, v)| first_difference(v, &y[k], &format!("{at}.{k}")))
        }
        (Value::Array(x), Value::Array(y)) if x.len() == y.len() => {
            x.iter().zip(y).enumerate().find_map(|(i, (v, w))| first_difference(v, w, &format!("{at}[{i}]")))
        }
        _ => (a != b).then(|| format!("{at}: committed {a} vs regenerated {b}")),
    }
}

#[test]
fn fixtures_are_what_the_script_makes() {
    let python = "/usr/bin/python3";
    let have =
        Command::new(python).args(["-c", "import pyopenvdb"]).output().map(|o| o.status.success()).unwrap_or(false);
    if !have {
        assert!(std::env::var_os("CI").is_none(), "CI must install python3-openvdb to regenerate the VDB fixtures");
        eprintln!("skipping: /usr/bin/python3 cannot import pyopenvdb (apt-get install python3-openvdb)");
        return;
    }
    let committed = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/vdb");
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().to_path_buf();
    let run = Command::new(python).arg(committed.join("make_fixtures.py")).arg("--out").arg(&out).output().unwrap();
    assert!(
        run.status.success(),
        "make_fixtures.py failed:\n{}{}",
        String::from_utf8_lossy(&run.stdout),
        String::from_utf8_lossy(&run.stderr)
    );
    let regenerate = "regenerate with /usr/bin/python3 modeler/tests/data/vdb/make_fixtures.py";
    for name in FIXTURES {
        let read_json = |dir: &Path| -> Value {
            serde_json::from_str(&std::fs::read_to_string(dir.join(format!("{name}.json"))).unwrap()).unwrap()
        };
        let (want, got) = (read_json(&committed), read_json(&out));
        if let Some(d) = first_difference(&want, &got, name) {
            panic!("{name}.json differs from the script's output at {d}; {regenerate}");
        }
        let (a, b) = (
            std::fs::read(committed.join(format!("{name}.vdb"))).unwrap(),
            std::fs::read(out.join(format!("{name}.vdb"))).unwrap(),
        );
        let at = a.iter().zip(&b).position(|(x, y)| x != y);
        assert!(
            a == b,
            "{name}.vdb differs from the script's output ({} vs {} bytes, first difference at {at:?}); {regenerate}",
            a.len(),
            b.len()
        );
    }
}

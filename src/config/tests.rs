//! Tests of the settings each command's flags become.
use super::*;

/// `run`'s flags are validated here, each error naming its flag
/// (code-habits audit: they were checked inline in `app/`).
#[test]
fn run_flags_are_validated_naming_the_flag() {
    let args = |extra: &[&str]| {
        let mut v = vec!["brickworld", "run"];
        v.extend_from_slice(extra);
        match <crate::cli::Cli as clap::Parser>::try_parse_from(v)
            .unwrap()
            .command
        {
            crate::cli::Command::Run(a) => a,
            _ => unreachable!(),
        }
    };
    let ok = RunSettings::from_args(&args(&[
        "--addr",
        "127.0.0.1:9",
        "--memory-budget",
        "1.5GiB",
        "--ticks",
        "3",
    ]))
    .unwrap();
    assert_eq!(ok.addr, Some("127.0.0.1:9".parse().unwrap()));
    assert_eq!(ok.memory_budget, Some(3 << 29));
    assert_eq!(ok.ticks, Some(3));
    for (flags, says) in [
        (&["--addr", "box.lan:1"][..], "invalid --addr 'box.lan:1'"),
        (
            &["--memory-budget", "lots"],
            "invalid --memory-budget 'lots'",
        ),
        (&["--ticks", "0"], "invalid --ticks '0'"),
    ] {
        let e = RunSettings::from_args(&args(flags)).unwrap_err();
        assert!(e.to_string().starts_with(says), "{e}");
    }
}

/// Regression (review): `render` applied `--fov` to the scene's default
/// view, `sim` ignored it there. Both take their camera from here: an
/// explicit view as given, the default one with `--fov`.
#[test]
fn the_fov_flag_applies_to_the_default_view_and_an_explicit_view_stands() {
    let default = View {
        eye: [0.0, 10.0, -20.0],
        target: [0.0, 0.0, 0.0],
        fov: 50.0,
    };
    let mut v = ViewSettings {
        view: None,
        fov: Some(20.0),
        width: 32,
        height: 16,
        threads: None,
    };
    let cam = v.camera(default).unwrap();
    assert_eq!(cam.fov_deg, 20.0);
    assert_eq!(cam.eye, DVec3::new(0.0, 10.0, -20.0));
    assert_eq!((cam.width, cam.height), (32, 16));
    v.fov = None;
    assert_eq!(v.camera(default).unwrap().fov_deg, 50.0);
    v.view = Some(View {
        eye: [1.0, 2.0, 3.0],
        target: [4.0, 0.0, 6.0],
        fov: 35.0,
    });
    v.fov = Some(20.0);
    let cam = v.camera(default).unwrap();
    assert_eq!((cam.eye, cam.fov_deg), (DVec3::new(1.0, 2.0, 3.0), 35.0));
}

//! `forja-sim --plot` on printer jobs: the slicer corpus, layers chosen with `--plot-layers`,
//! and the errors of a bad choice; the steps of a trace held to the toolpath.

mod common;

use std::path::{Path, PathBuf};
use std::process::Output;

use common::sim;

fn temp_path(name: &str) -> PathBuf {
    std::env::temp_dir().join(format!("forja-sim-plot-{}-{name}", std::process::id()))
}

/// A job of the slicer corpus.
fn corpus(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../tests/corpus/slicers")
        .join(name)
}

/// `forja-sim --machine builtin:printer --job JOB --check --plot OUT` and `extra`.
fn check_plot(job: &Path, out: &Path, extra: &[&str]) -> Output {
    sim()
        .args(["--machine", "builtin:printer", "--check", "--job"])
        .arg(job)
        .arg("--plot")
        .arg(out)
        .args(extra)
        .output()
        .unwrap()
}

fn stdout(out: &Output) -> String {
    String::from_utf8_lossy(&out.stdout).into_owned()
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// A small printer job: homing, a purge line at 0.3 mm, then three layers of a 20 mm square.
const PART: &str = "G28\nM83\nG1 Z0.3 F600\nG1 X5 Y60 E5 F1200\nG1 E-0.8 F2100\n\
    G0 Z0.2\nG0 X100 Y100\nG1 E0.8\nG1 X120 Y100 E1\nG1 X120 Y120 E1\n\
    G1 Z0.4\nG0 X100 Y100\nG1 X120 Y100 E1\n\
    G1 Z0.6\nG0 X105 Y105\nG1 X115 Y105 E1\nG1 E-0.8\nG0 Z10\nG0 X0 Y200\n";

#[test]
fn every_slicer_file_plots_by_layer_and_one_layer_alone() {
    for (file, layers, heights) in [
        ("prusaslicer.gcode", 6, "Z 0.2 to 1.2 mm"),
        ("cura.gcode", 6, "Z 0.2 to 1.2 mm"),
        ("orcaslicer.gcode", 5, "Z 0.2 to 1 mm"),
        ("superslicer.gcode", 5, "Z 0.2 to 1 mm"),
    ] {
        let job = corpus(file);
        let image = temp_path(&format!("{file}.png"));
        // Nothing runs (--check): the job's own homing line places the part.
        let out = check_plot(&job, &image, &[]);
        let text = stdout(&out);
        // A line the kernel refuses is listed, and the check says the job would not run
        // cleanly; the plot is drawn all the same.
        let refused = text.contains("refused by the kernel: ");
        assert_eq!(
            out.status.code(),
            Some(if refused { 2 } else { 0 }),
            "{file}: {text}{}",
            stderr(&out)
        );
        assert!(std::fs::metadata(&image).unwrap().len() > 5000, "{file}");
        assert!(
            text.contains(&format!(": {layers} layers, Z ")),
            "{file}: {text}"
        );
        // Heights are the bed's once the job's homing line homes Z.
        if !refused {
            assert!(
                text.contains(&format!(": {layers} layers, {heights}; ")),
                "{file}: {text}"
            );
        }
        assert!(text.contains(" mm of extrusion ("), "{file}: {text}");
        let out = check_plot(&job, &image, &["--plot-layers", "2", "--plot-hide-travel"]);
        let text = stdout(&out);
        assert!(
            text.contains(&format!("drawn: layer 2 of {layers}, Z ")),
            "{file}: {text}"
        );
        std::fs::remove_file(&image).unwrap();
    }
}

#[test]
fn layers_are_counted_from_the_heights_of_extrusion_and_chosen_by_number() {
    let job = temp_path("part.gcode");
    std::fs::write(&job, PART).unwrap();
    let image = temp_path("part.svg");
    let out = check_plot(&job, &image, &[]);
    let text = stdout(&out);
    assert!(out.status.success(), "{text}{}", stderr(&out));
    // 100 mm of extrusion: the purge line (55 mm, on layer 1), then 40, 20 and 10 mm.
    assert!(
        text.contains(": 3 layers, Z 0.2 to 0.6 mm; 125.0 mm of extrusion (9.0 mm of filament), "),
        "{text}"
    );
    assert!(text.contains(", 2 retractions"), "{text}");
    for (layers, drawn) in [
        ("1", "layer 1 of 3, Z 0.2 to 0.3 mm"),
        ("2..3", "layers 2 to 3 of 3, Z 0.4 to 0.6 mm"),
        ("2..", "layers 2 to 3 of 3, Z 0.4 to 0.6 mm"),
        ("..2", "layers 1 to 2 of 3, Z 0.2 to 0.4 mm"),
    ] {
        let out = check_plot(&job, &image, &["--plot-layers", layers]);
        let text = stdout(&out);
        assert!(out.status.success(), "{layers}: {text}{}", stderr(&out));
        assert!(
            text.contains(&format!("\ndrawn: {drawn}\n")),
            "{layers}: {text}"
        );
        assert!(std::fs::metadata(&image).unwrap().len() > 1000);
    }
    // The job run, its steps drawn at the chosen layer's height.
    let out = sim()
        .args(["--machine", "builtin:printer", "--no-home", "--job"])
        .arg(&job)
        .arg("--plot")
        .arg(&image)
        .args(["--plot-layers", "3"])
        .output()
        .unwrap();
    let text = stdout(&out);
    assert!(out.status.success(), "{text}{}", stderr(&out));
    assert!(text.contains("\ndrawn: layer 3 of 3, Z 0.6 mm\n"), "{text}");
    assert!(
        text.contains("ends 0.000 mm from the program's end"),
        "{text}"
    );
    std::fs::remove_file(&job).unwrap();
    std::fs::remove_file(&image).unwrap();
}

#[test]
fn a_bad_layer_choice_is_an_error_that_names_the_option() {
    let job = temp_path("bad-layers.gcode");
    std::fs::write(&job, PART).unwrap();
    let image = temp_path("bad-layers.png");
    for (layers, why) in [
        ("0", "--plot-layers 0: layers are numbered from 1"),
        (
            "3..2",
            "--plot-layers 3..2: the range ends before it starts",
        ),
        (
            "two",
            "--plot-layers two: give a layer (3) or a range of layers",
        ),
        (
            "4",
            "--plot-layers 4: the job has 3 layers, Z 0.2 to 0.6 mm",
        ),
        ("2..7", "--plot-layers 2..7: the job has 3 layers"),
    ] {
        let out = check_plot(&job, &image, &["--plot-layers", layers]);
        assert_eq!(out.status.code(), Some(1), "{layers}: {out:?}");
        let err = stderr(&out);
        assert!(
            err.starts_with(&format!("forja-sim: {why}")),
            "{layers}: {err}"
        );
        assert!(!image.exists(), "{layers}: no plot is drawn");
    }
    // Checked before the job runs.
    let out = sim()
        .args(["--machine", "builtin:printer", "--job"])
        .arg(&job)
        .arg("--plot")
        .arg(&image)
        .args(["--plot-layers", "9"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(!stdout(&out).contains("result:"), "{}", stdout(&out));
    assert!(stderr(&out).contains("--plot-layers 9: the job has 3 layers"));
    // A machine without an extruder has no layers.
    let out = sim()
        .args(["--check", "--plot"])
        .arg(&image)
        .args(["--plot-layers", "1"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(
        stderr(&out).contains("--plot-layers 1: layers are the heights at which an extruder"),
        "{}",
        stderr(&out)
    );
    std::fs::remove_file(&job).unwrap();
}

#[test]
fn a_refused_line_is_listed_marked_and_makes_the_check_fail() {
    let job = temp_path("refused.gcode");
    std::fs::write(
        &job,
        "G28\nM83\nG1 Z0.2 F600\nG1 X100 Y100\nG1 Q5\nG1 X120 E1\n",
    )
    .unwrap();
    let image = temp_path("refused.png");
    let out = check_plot(&job, &image, &[]);
    assert_eq!(out.status.code(), Some(2), "{out:?}");
    let text = stdout(&out);
    assert!(
        text.contains(&format!(
            "refused by the kernel: {}, line 5: G1Q5: ",
            job.display()
        )),
        "{text}"
    );
    assert!(text.contains("(E127"), "{text}");
    // The rest of the job is drawn: one layer, from (100, 100) to (120, 100).
    assert!(
        text.contains(": 1 layer, Z 0.2 mm; 20.0 mm of extrusion"),
        "{text}"
    );
    assert!(stderr(&out).contains("refuses 1 of the job's lines"));
    assert!(std::fs::metadata(&image).unwrap().len() > 1000);
    std::fs::remove_file(&job).unwrap();
    std::fs::remove_file(&image).unwrap();
}

/// `trace: farthest from the toolpath D mm (one step: S mm)` in `text`: D and S.
fn farthest(text: &str) -> (f64, f64) {
    let line = text
        .lines()
        .find_map(|l| l.strip_prefix("trace: farthest from the toolpath "))
        .unwrap_or_else(|| panic!("no trace line: {text}"));
    let number = |s: &str| -> f64 { s.parse().unwrap_or_else(|_| panic!("{line}")) };
    let (d, rest) = line.split_once(" mm (one step: ").expect(line);
    let (s, _) = rest.split_once(" mm)").expect(line);
    (number(d), number(s))
}

#[test]
fn the_sample_jobs_steps_stay_within_one_step_of_its_toolpath() {
    let job = Path::new(env!("CARGO_MANIFEST_DIR")).join("jobs/sample.gcode");
    let image = temp_path("sample.svg");
    let out = sim()
        .arg("--job")
        .arg(&job)
        .arg("--plot")
        .arg(&image)
        .output()
        .unwrap();
    let text = stdout(&out);
    assert!(out.status.success(), "{text}{}", stderr(&out));
    // Every position the machine passed through from the G28 on (the homing cycle left out),
    // X/Y/Z: the router's X and Y make 80 steps a mm, Z 400.
    let (distance, step) = farthest(&text);
    assert_eq!(step, 0.0125, "{text}");
    assert!(distance > 0.0 && distance <= step, "{text}");
    assert!(std::fs::metadata(&image).unwrap().len() > 1000);
    std::fs::remove_file(&image).unwrap();
}

/// A short router job with its own homing: a line, an arc, a lift.
const HOMED: &str = "G21 G90\nG28\nG0 X10 Y10 Z20\nG1 X40 F3000\nG1 Y30\nG2 X30 Y40 I-10 J0\n\
    G0 Z30\n";

#[test]
fn a_trace_drawn_over_another_job_fails_the_plot_naming_where_the_steps_strayed() {
    let job = temp_path("homed.gcode");
    std::fs::write(&job, HOMED).unwrap();
    let trace = temp_path("homed.trace");
    let out = sim()
        .args(["--no-home", "--job"])
        .arg(&job)
        .arg("--trace")
        .arg(&trace)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}{}", stdout(&out), stderr(&out));
    let image = temp_path("homed.svg");
    let check = |job: &Path| {
        sim()
            .args(["--check", "--job"])
            .arg(job)
            .arg("--plot")
            .arg(&image)
            .arg("--plot-trace")
            .arg(&trace)
            .output()
            .unwrap()
    };
    // Its own job: the homing cycle is left out, the rest within a step.
    let out = check(&job);
    let text = stdout(&out);
    assert!(out.status.success(), "{text}{}", stderr(&out));
    let (distance, step) = farthest(&text);
    assert!(distance <= step, "{text}");
    // The same job 1 mm to the right from line 3 on: the plot is drawn, and fails.
    let shifted = temp_path("shifted.gcode");
    std::fs::write(
        &shifted,
        HOMED
            .replace("X10 ", "X11 ")
            .replace("X40 ", "X41 ")
            .replace("X30 ", "X31 "),
    )
    .unwrap();
    let out = check(&shifted);
    assert_eq!(out.status.code(), Some(1), "{out:?}");
    let err = stderr(&out);
    assert!(err.starts_with("forja-sim: the steps strayed 1.0"), "{err}");
    assert!(
        err.contains(" mm from the toolpath at X")
            && err.contains(", more than one step (0.0125 mm)"),
        "{err}"
    );
    assert!(err.contains(" (line "), "{err}");
    let (distance, _) = farthest(&stdout(&out));
    assert!((1.0..1.02).contains(&distance), "{}", stdout(&out));
    assert!(std::fs::metadata(&image).unwrap().len() > 1000);
    // A trace of the job without its G28 never comes to where the job goes on after it.
    std::fs::write(&shifted, HOMED.replace("G28\n", "")).unwrap();
    let out = sim()
        .args(["--no-home", "--job"])
        .arg(&shifted)
        .arg("--trace")
        .arg(&trace)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", stderr(&out));
    let out = check(&job);
    assert_eq!(out.status.code(), Some(1), "{out:?}");
    assert!(
        stderr(&out).starts_with(
            "forja-sim: the steps never come to X2.000 Y2.000 Z99.000, where the program goes \
             on after homing (line 3)"
        ),
        "{}",
        stderr(&out)
    );
    for file in [&job, &shifted, &trace, &image] {
        std::fs::remove_file(file).unwrap();
    }
}

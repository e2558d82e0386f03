//! The Gray-code decoder against OpenCV's `getProjPixel` and against simulated ground truth.

use glasscan::decode::graycode::decode_view;
use glasscan::mesh::shapes::ellipsoid;
use glasscan::patterns::GrayCode;
use glasscan::simulate::{fixed_point_scale, simulate, SimulateOptions};
use nalgebra::Vector3;
use opencv::core::{Mat, MatTraitConst, MatTraitConstManual, Point, Vec4w, Vector};
use opencv::prelude::*;
use opencv::structured_light::{GrayCodePattern, GrayCodePattern_Params};

#[test]
fn agrees_with_opencv_and_keeps_the_reliable_bits_through_glass() {
    let dir = tempfile::tempdir().unwrap();
    let opts = SimulateOptions {
        views: 1,
        width: 200,
        height: 150,
        screen_width: 320,
        screen_height: 200,
        pitch_mm: 1.2,
        spp: 16,
        ..Default::default()
    };
    simulate(
        &ellipsoid(Vector3::new(30.0, 22.0, 18.0), 4),
        dir.path(),
        &opts,
        |_| (),
    )
    .unwrap();
    let code = GrayCode {
        width: opts.screen_width,
        height: opts.screen_height,
    };
    let load = |name: &str| {
        opencv::imgcodecs::imread(dir.path().join(name), opencv::imgcodecs::IMREAD_UNCHANGED)
            .unwrap()
    };
    let mats: Vec<Mat> = code.file_names()[..code.pattern_count()]
        .iter()
        .map(|n| load(&format!("captures/view_000/{n}")))
        .collect();
    let slices: Vec<&[u8]> = mats.iter().map(|m| m.data_typed::<u8>().unwrap()).collect();
    let decoded = decode_view(&slices, &code, 5);

    let mut params = GrayCodePattern_Params::default().unwrap();
    params.set_width(code.width as i32);
    params.set_height(code.height as i32);
    let opencv = GrayCodePattern::create(&params).unwrap();
    let images: Vector<Mat> = mats.iter().cloned().collect();
    let (mut complete, mut partial) = (0, 0);
    for y in 0..150 {
        for x in 0..200 {
            let d = decoded[(y * 200 + x) as usize];
            let mut p = Point::default();
            let error = opencv.get_proj_pixel(&images, x, y, &mut p).unwrap();
            assert_eq!(
                !error,
                d.complete(&code),
                "pixel ({x}, {y}): OpenCV error {error}, ours {d:?}"
            );
            if !error {
                assert_eq!(
                    (p.x as f32, p.y as f32),
                    (d.u.coord, d.v.coord),
                    "pixel ({x}, {y})"
                );
                complete += 1;
            } else if d.u.bits > 0 && d.v.bits > 0 {
                partial += 1;
            }
        }
    }
    assert!(complete > 10_000, "{complete} complete pixels");
    // Through the glass, the antialiased finest stripes blur: pixels OpenCV rejects keep their
    // coarse bits, and the footprint centroid lies in the cell they select.
    let foot = load("truth/view_000_footprint.png");
    let s = fixed_point_scale(code.width, code.height) as f32;
    let (mut inside, mut checked) = (0, 0);
    for y in 0..150 {
        for x in 0..200 {
            let d = decoded[(y * 200 + x) as usize];
            let f = *foot.at_2d::<Vec4w>(y, x).unwrap();
            if d.complete(&code)
                || d.u.bits == 0
                || d.v.bits == 0
                || f[0] == u16::MAX
                || f[3] < 65535
            {
                continue;
            }
            let (cu, cv) = (f[0] as f32 / s - 1.0, f[1] as f32 / s - 1.0);
            checked += 1;
            if (cu - d.u.coord).abs() <= d.u.cell as f32 / 2.0 + 0.5
                && (cv - d.v.coord).abs() <= d.v.cell as f32 / 2.0 + 0.5
            {
                inside += 1;
            }
        }
    }
    assert!(
        partial > 100 && checked > 100,
        "{partial} partial, {checked} checked"
    );
    assert!(
        inside as f64 >= 0.9 * checked as f64,
        "footprint centroid inside the cell for {inside} of {checked}"
    );
}

use super::*;

fn ring(n: usize, centre: [f32; 3], r: f32, elev_deg: f32) -> Vec<PathCamera> {
    let rig = SceneRig {
        centre,
        up: [0.0, 1.0, 0.0],
        distance: r,
        elevation: elev_deg.to_radians(),
        azimuth: 0.3,
        fov_y_deg: 40.0,
        ..SceneRig::default_object()
    };
    rig.orbit(n)
}

fn close(a: f32, b: f32, tol: f32) -> bool {
    (a - b).abs() <= tol
}

#[test]
fn orbit_cameras_look_at_the_centre_from_the_mean_distance_and_elevation() {
    // Cameras as a capture might place them: a ring 1.2 from (0.4, 0.55, 0.6), 25° up.
    let centre = [0.4, 0.55, 0.6];
    let captured = ring(24, centre, 1.2, 25.0);
    let rig = SceneRig::of(&captured, [0.5; 3]).unwrap();
    assert!(dist(rig.centre, centre) < 2e-4, "centre {:?}", rig.centre);
    assert!(close(rig.distance, 1.2, 1e-4));
    assert!(close(rig.elevation.to_degrees(), 25.0, 1e-2));
    assert!(close(rig.fov_y_deg, 40.0, 1e-4));
    let orbit = rig.orbit(36);
    assert_eq!(orbit.len(), 36);
    for c in &orbit {
        let cam = c.camera(320, 240);
        let [u, v] = cam.project(centre).expect("the centre is in front");
        assert!(
            close(u, 160.0, 1e-2) && close(v, 120.0, 1e-2),
            "centre at ({u}, {v})"
        );
        // Upright: the camera's down axis points away from up.
        assert!(cam.axis(1)[1] < 0.0);
        let p = cam.position();
        assert!(close(dist(p, centre), 1.2, 1e-4));
    }
    // The first orbit camera starts where the capture's first camera stands.
    let p0 = orbit[0].camera(8, 8).position();
    let q0 = captured[0].camera(8, 8).position();
    assert!(dist(p0, q0) < 1e-4, "{p0:?} vs {q0:?}");
}

#[test]
fn look_at_is_a_right_handed_rotation() {
    let m = look_at([1.0, 2.0, 3.0], [0.5, 0.5, 0.5], [0.0, 1.0, 0.0]);
    let col = |k: usize| [m[0][k], m[1][k], m[2][k]];
    for k in 0..3 {
        assert!(close(norm(col(k)), 1.0, 1e-5));
    }
    assert!(close(dot(cross(col(0), col(1)), col(2)), 1.0, 1e-5));
    // Straight down the up axis still gives a rotation.
    let m = look_at([0.5, 2.0, 0.5], [0.5, 0.5, 0.5], [0.0, 1.0, 0.0]);
    let col = |k: usize| [m[0][k], m[1][k], m[2][k]];
    assert!(close(dot(cross(col(0), col(1)), col(2)), 1.0, 1e-5));
}

#[test]
fn spiral_stays_near_the_cameras_and_looks_ahead() {
    // Forward-facing: cameras on a small plane patch, all looking along +z.
    let cams: Vec<PathCamera> = (0..20)
        .map(|i| {
            let (x, y) = ((i % 5) as f32 * 0.02, (i / 5) as f32 * 0.02);
            PathCamera {
                c2w: [
                    [1.0, 0.0, 0.0, 0.45 + x],
                    [0.0, 1.0, 0.0, 0.45 + y],
                    [0.0, 0.0, 1.0, 0.0],
                ],
                fov_y_deg: 45.0,
            }
        })
        .collect();
    let rig = SceneRig::of(&cams, [0.5; 3]).unwrap();
    // Parallel axes never meet: the box centre stands in.
    assert_eq!(rig.centre, [0.5; 3]);
    let spiral = rig.spiral(60);
    for c in &spiral {
        let cam = c.camera(100, 100);
        let p = cam.position();
        assert!(dist(p, rig.mean_position) < 0.2, "{p:?}");
        assert!(cam.axis(2)[2] > 0.9, "looks ahead: {:?}", cam.axis(2));
    }
    // It moves: two turns of the ellipse.
    assert!(
        dist(
            spiral[0].camera(8, 8).position(),
            spiral[15].camera(8, 8).position()
        ) > 0.01
    );
}

#[test]
fn nerf_frame_round_trips() {
    let frame = NerfFrame {
        scale: 0.25,
        offset: [0.5, 0.4, 0.6],
    };
    let nerf = [
        [0.0, -1.0, 0.0, 1.0],
        [1.0, 0.0, 0.0, -2.0],
        [0.0, 0.0, 1.0, 0.5],
    ];
    let back = frame.to_nerf(&frame.to_ngp(&nerf));
    for i in 0..3 {
        for j in 0..4 {
            assert!(close(back[i][j], nerf[i][j], 1e-6), "{back:?}");
        }
    }
}

#[test]
fn quaternions_round_trip() {
    for c in ring(10, [0.5; 3], 1.0, 40.0) {
        let rot = [
            [c.c2w[0][0], c.c2w[0][1], c.c2w[0][2]],
            [c.c2w[1][0], c.c2w[1][1], c.c2w[1][2]],
            [c.c2w[2][0], c.c2w[2][1], c.c2w[2][2]],
        ];
        let back = quat_to_mat(mat_to_quat(rot));
        for i in 0..3 {
            for j in 0..3 {
                assert!(close(back[i][j], rot[i][j], 1e-5));
            }
        }
    }
}

fn same_cameras(a: &[PathCamera], b: &[PathCamera], tol: f32) {
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(b) {
        for i in 0..3 {
            for j in 0..4 {
                assert!(
                    close(x.c2w[i][j], y.c2w[i][j], tol),
                    "{:?} vs {:?}",
                    x.c2w,
                    y.c2w
                );
            }
        }
        assert!(close(x.fov_y_deg, y.fov_y_deg, tol));
    }
}

#[test]
fn nerfstudio_files_round_trip() {
    let frame = NerfFrame {
        scale: 0.2,
        offset: [0.5, 0.5, 0.5],
    };
    let path = CameraPath {
        cameras: ring(12, [0.5; 3], 1.3, 20.0),
        fps: 30.0,
        size: Some((64, 48)),
    };
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("camera_path.json");
    write_nerfstudio(&file, &path, 64, 48, &frame).unwrap();
    let back = read_path(&file, None, &frame).unwrap();
    assert_eq!(back.fps, 30.0);
    assert_eq!(back.size, Some((64, 48)));
    same_cameras(&back.cameras, &path.cameras, 1e-5);
    // A frame count is refused for a file that lists its frames.
    let e = read_path(&file, Some(10), &frame).unwrap_err().to_string();
    assert!(e.contains("--frames"), "{e}");
}

#[test]
fn instant_ngp_keyframes_round_trip_through_the_spline() {
    let path = CameraPath {
        cameras: ring(8, [0.5; 3], 1.0, 30.0),
        fps: 24.0,
        size: None,
    };
    let v = instant_ngp_json(&path);
    let text = serde_json::to_string(&v).unwrap();
    // With a linear spline and n keyframes, frame i of n − 1 is keyframe i.
    let back = parse_path(
        Path::new("base_cam.json"),
        &text,
        Some(7),
        &NerfFrame::default(),
    )
    .unwrap();
    same_cameras(&back.cameras, &path.cameras[..7], 1e-4);
    // The default cubic spline passes near, not through, its keyframes, and stays on the ring.
    let mut cubic = v.clone();
    cubic["spline_order"] = json!(3);
    let back = parse_path(
        Path::new("b.json"),
        &cubic.to_string(),
        Some(70),
        &NerfFrame::default(),
    )
    .unwrap();
    for c in &back.cameras {
        let p = c.camera(8, 8).position();
        let r = dist(p, [0.5; 3]);
        assert!(r > 0.85 && r < 1.01, "{r}");
    }
}

#[test]
fn instant_ngp_reference_file_shape_parses() {
    // The shape instant-ngp's CameraPath::save writes (R is x, y, z, w).
    let text = r#"{"loop":false,"time":1.0,"duration_seconds":2.0,"spline_order":3,"path":[
        {"R":[0.0,0.0,0.0,1.0],"T":[0.5,0.5,-1.0],"slice":0.0,"scale":1.0,"fov":50.625,"aperture_size":0.0,"timestamp":0.5},
        {"R":[0.0,0.3826834,0.0,0.9238795],"T":[1.2,0.5,-0.2],"slice":0.0,"scale":1.0,"fov":50.625,"aperture_size":0.0,"timestamp":1.0}]}"#;
    let p = parse_path(
        Path::new("base_cam.json"),
        text,
        Some(5),
        &NerfFrame::default(),
    )
    .unwrap();
    assert_eq!(p.cameras.len(), 5);
    // The first frame is the first keyframe: identity rotation looks along +z from T.
    let c = p.cameras[0].camera(10, 10);
    assert!(dist(c.position(), [0.5, 0.5, -1.0]) < 0.2);
    assert!(close(p.cameras[0].fov_y_deg, 50.625, 1e-4));
}

#[test]
fn malformed_paths_name_the_field() {
    let cases: &[(&str, &str)] = &[
        ("[]", "JSON object"),
        ("{", "not JSON"),
        (r#"{"x":1}"#, "neither"),
        (r#"{"camera_path":[]}"#, "camera_path: no cameras"),
        (
            r#"{"camera_path":[{"camera_to_world":[1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]}]}"#,
            "camera_path[0].fov: missing",
        ),
        (
            r#"{"camera_path":[{"camera_to_world":[1,0,0], "fov":50}]}"#,
            "camera_path[0].camera_to_world: 3 numbers",
        ),
        (
            r#"{"camera_path":[{"camera_to_world":[2,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1], "fov":50}]}"#,
            "column 0",
        ),
        (
            r#"{"camera_path":[{"camera_to_world":[1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1], "fov":500}]}"#,
            "camera_path[0].fov: 500",
        ),
        (r#"{"render_width":-3,"camera_path":[]}"#, "render_width"),
        (
            r#"{"camera_type":"fisheye","camera_path":[]}"#,
            "camera_type",
        ),
        (
            r#"{"fps":"fast","camera_path":[{"camera_to_world":[1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1], "fov":50}]}"#,
            "fps: expected a number",
        ),
        (
            r#"{"path":[{"R":[0,0,0,0],"T":[0,0,0],"fov":50}]}"#,
            "path[0].R: a zero quaternion",
        ),
        (
            r#"{"path":[{"R":[0,0,0,1],"T":[0,"a",0],"fov":50}]}"#,
            "path[0].T[1]: expected a number",
        ),
        (
            r#"{"path":[{"R":[0,0,0,1],"T":[0,0,0],"fov":50}], "spline_order": 7}"#,
            "spline_order",
        ),
        (r#"{"path":{}}"#, "path: expected an array"),
        (
            r#"{"camera_path":[{"camera_to_world":[1e39,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1], "fov":50}]}"#,
            "finite",
        ),
    ];
    for (text, says) in cases {
        let e = parse_path(
            Path::new("paths/bad.json"),
            text,
            None,
            &NerfFrame::default(),
        )
        .expect_err(text)
        .to_string();
        assert!(e.contains("paths/bad.json"), "{e}");
        assert!(e.contains(says), "{text}: {e} (wanted {says})");
    }
}

#[test]
fn a_capture_from_one_side_is_swept_over_its_arc() {
    // Cameras over 120° of a circle: the sweep stays within it, a full ring surrounds.
    let full = SceneRig::of(&ring(24, [0.5; 3], 1.0, 20.0), [0.5; 3]).unwrap();
    assert!(full.surrounds());
    let part: Vec<PathCamera> = ring(36, [0.5; 3], 1.0, 20.0).into_iter().take(12).collect();
    let rig = SceneRig::of(&part, [0.5; 3]).unwrap();
    assert!(!rig.surrounds());
    assert!(
        close(rig.arc_span.to_degrees(), 110.0, 0.5),
        "{}",
        rig.arc_span.to_degrees()
    );
    let inside = |p: [f32; 3]| {
        part.iter()
            .map(|c| dist(c.camera(8, 8).position(), p))
            .fold(f32::INFINITY, f32::min)
            < 0.2
    };
    let sweep = rig.sweep(30);
    for c in &sweep {
        let p = c.camera(8, 8).position();
        assert!(inside(p), "{p:?} is outside the cameras' arc");
        assert!(close(dist(p, rig.centre), 1.0, 1e-3));
    }
    // It reaches both ends of the arc.
    let ends = [
        part[0].camera(8, 8).position(),
        part[11].camera(8, 8).position(),
    ];
    for e in ends {
        assert!(
            sweep
                .iter()
                .any(|c| dist(c.camera(8, 8).position(), e) < 0.05),
            "{e:?} not reached"
        );
    }
}

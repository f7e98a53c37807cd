//! `prac render`: every domain draws to a PNG of the asked size; a policy's plan is overlaid.

use std::process::Command;

fn png_size(bytes: &[u8]) -> (u32, u32) {
    assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n");
    let be = |i: usize| u32::from_be_bytes([bytes[i], bytes[i + 1], bytes[i + 2], bytes[i + 3]]);
    (be(16), be(20))
}

/// How many pixels of the picture have exactly this colour.
fn pixels_of(bytes: &[u8], colour: [u8; 3]) -> usize {
    let picture = image::load_from_memory(bytes).unwrap().to_rgb8();
    picture.pixels().filter(|p| p.0 == colour).count()
}

/// Pixels above row `rows` that are clearly red: the plan's colour, alone or faded.
fn reddish_pixels_above(bytes: &[u8], rows: u32) -> usize {
    let picture = image::load_from_memory(bytes).unwrap().to_rgb8();
    let red = |p: &image::Rgb<u8>| {
        let [r, g, b] = p.0.map(i32::from);
        r > g + 60 && r > b + 60
    };
    let (width, _) = picture.dimensions();
    (0..rows)
        .flat_map(|y| (0..width).map(move |x| (x, y)))
        .filter(|&(x, y)| red(picture.get_pixel(x, y)))
        .count()
}

/// The robot's (or lander's, or pendulum's) colour in `prac render`.
const BODY: [u8; 3] = [80, 90, 160];

#[test]
fn every_domain_renders_and_a_plan_is_overlaid() {
    let dir = tempfile::tempdir().unwrap();
    for domain in prac::domains::DOMAINS {
        let out = dir.path().join(format!("{domain}.png"));
        let run = Command::new(env!("CARGO_BIN_EXE_prac"))
            .args([
                "render", domain, "--seed", "2", "--width", "320", "--height", "200",
            ])
            .arg("--out")
            .arg(&out)
            .output()
            .unwrap();
        assert!(
            run.status.success(),
            "{}",
            String::from_utf8_lossy(&run.stderr)
        );
        let bytes = std::fs::read(&out).unwrap();
        assert_eq!(png_size(&bytes), (320, 200));
        // The body is drawn, not only the frame around it.
        let body = pixels_of(&bytes, BODY);
        assert!(body >= 20, "{domain}: {body} body pixels");
        if *domain == "pendulum" {
            // Without a policy there is no plan to draw.
            assert_eq!(reddish_pixels_above(&bytes, 200), 0);
        }
        let env = prac::domains::make(domain).unwrap();
        assert!(
            env.scene()
                .shapes
                .iter()
                .any(|(part, _)| *part == prac::domains::Part::Body),
            "{domain} draws no body"
        );
    }
    let bundle =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("bundles/pendulum.safetensors");
    let out = dir.path().join("plan.png");
    let run = Command::new(env!("CARGO_BIN_EXE_prac"))
        .args([
            "render",
            "pendulum",
            "--seed",
            "3",
            "--steps",
            "30",
            "--epsilon-coef",
            "0.01",
        ])
        .arg("--policy")
        .arg(&bundle)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    // The default size, its lower third the forecast panel.
    let bytes = std::fs::read(&out).unwrap();
    assert_eq!(png_size(&bytes), (800, 640));
    // The imagined states are drawn over the scene in the plan's red (faded with distance).
    let plan = reddish_pixels_above(&bytes, 400);
    assert!(plan >= 20, "{plan} plan pixels");
    let stdout = String::from_utf8_lossy(&run.stdout);
    let drawn: usize = stdout
        .split('(')
        .nth(1)
        .and_then(|s| s.split_whitespace().next())
        .and_then(|n| n.parse().ok())
        .unwrap();
    assert!(drawn > 1, "{stdout}");
    // A policy for another domain is refused.
    let wrong = Command::new(env!("CARGO_BIN_EXE_prac"))
        .args(["render", "lander", "--steps", "1"])
        .arg("--policy")
        .arg(&bundle)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(!wrong.status.success());
    assert!(String::from_utf8_lossy(&wrong.stderr).contains("not 'lander'"));
}

#[test]
fn traces_follow_the_predicted_observations() {
    let mut env = prac::domains::make("pendulum").unwrap();
    let mut obs = vec![0.0f32; 3];
    env.reset(0, &mut obs).unwrap();
    let theta = 0.4f32;
    let trace = env.trace(&[theta.cos(), theta.sin(), 0.0]);
    assert!((trace[0].0 - f64::from(theta.sin())).abs() < 1e-6);
    assert!((trace[0].1 - f64::from(theta.cos())).abs() < 1e-6);

    // The lander's trace inverts its observation's position normalisation.
    let mut lander = prac::domains::make("lander").unwrap();
    let mut obs = vec![0.0f32; 8];
    lander.reset(0, &mut obs).unwrap();
    let scene = lander.scene();
    let start = lander.trace(&obs)[0];
    assert!((start.0 - scene.center.0).abs() < 1.0, "{start:?}");
    assert!(
        start.1 > scene.center.1,
        "the lander starts high: {start:?}"
    );
}

#[test]
fn a_picture_into_a_missing_folder_is_a_plain_error() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("missing/pendulum.png");
    let run = Command::new(env!("CARGO_BIN_EXE_prac"))
        .args(["render", "pendulum", "--seed", "1", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(!run.status.success());
    let err = String::from_utf8_lossy(&run.stderr);
    assert!(
        err.contains("the folder") && err.contains("does not exist"),
        "{err}"
    );
    assert!(!err.contains("IoError"), "{err}");
}

#[test]
fn a_tolerance_without_a_policy_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let run = Command::new(env!("CARGO_BIN_EXE_prac"))
        .args(["render", "pendulum", "--epsilon-coef", "0.1", "--out"])
        .arg(dir.path().join("p.png"))
        .output()
        .unwrap();
    assert!(!run.status.success());
    assert!(String::from_utf8_lossy(&run.stderr).contains("--policy"));
}

#[test]
fn the_3d_robots_colour_their_limbs_by_side_and_the_lander_fits_its_view() {
    use prac::domains::Part;
    for domain in ["ant", "humanoid"] {
        let mut env = prac::domains::make(domain).unwrap();
        let mut obs = vec![0.0f32; env.spec().obs_dim];
        env.reset(1, &mut obs).unwrap();
        let parts: Vec<Part> = env.scene().shapes.iter().map(|(p, _)| *p).collect();
        for side in [Part::Left, Part::Right, Part::Body] {
            assert!(parts.contains(&side), "{domain} draws no {side:?} part");
        }
        let left = parts.iter().filter(|p| **p == Part::Left).count();
        let right = parts.iter().filter(|p| **p == Part::Right).count();
        assert_eq!(
            left, right,
            "{domain}: a symmetric robot has as many limbs on each side"
        );
    }
    // The lander starts at the top of its viewport: the view leaves room above it.
    let mut lander = prac::domains::make("lander").unwrap();
    let mut obs = vec![0.0f32; 8];
    lander.reset(3, &mut obs).unwrap();
    let scene = lander.scene();
    let top = scene.center.1 + scene.height / 2.0;
    let lander_y = lander.trace(&obs)[0].1;
    assert!(lander_y + 1.0 < top, "lander at {lander_y}, view top {top}");
}

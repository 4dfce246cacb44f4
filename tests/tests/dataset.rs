//! Training data: rendering analytic scans with the dataset renderer (normal maps against
//! analytic normals, mask areas against projected areas, texture colours), the camera
//! protocol's statistics, and the dataset reader's validation.

use getavatar_core::body::skinning::BodyParams;
use getavatar_core::io::dataset::{encode_png, labels_to_json, Dataset, Label};
use getavatar_core::io::scan::{parse_obj, render_scan, RenderableScan, Scan, SmplParams};
use getavatar_core::render::camera::{reference_fov_y, sample_data_camera, DATA_ELEVATION_STD};
use getavatar_core::render::rasterize::{RenderedViews, Texture};
use getavatar_core::util::rng::Rng;
use getavatar_core::OrbitCamera;
use glam::{Vec2, Vec3};

/// UV sphere OBJ text: `n_lon` × `n_lat` quads, u = longitude / 2π, v = latitude.
fn uv_sphere_obj(c: Vec3, r: f32, n_lon: usize, n_lat: usize) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    for i in 0..=n_lat {
        let th = std::f32::consts::PI * i as f32 / n_lat as f32; // 0 = top
        for k in 0..=n_lon {
            let ph = std::f32::consts::TAU * k as f32 / n_lon as f32;
            let d = Vec3::new(th.sin() * ph.sin(), th.cos(), th.sin() * ph.cos());
            let p = c + r * d;
            let _ = writeln!(
                s,
                "v {} {} {}\nvt {} {}",
                p.x,
                p.y,
                p.z,
                k as f32 / n_lon as f32,
                1.0 - i as f32 / n_lat as f32
            );
        }
    }
    let row = n_lon + 1;
    for i in 0..n_lat {
        for k in 0..n_lon {
            let (a, b, cc, d) = (i * row + k + 1, i * row + k + 2, (i + 1) * row + k + 1, (i + 1) * row + k + 2);
            let _ = writeln!(s, "f {a}/{a} {cc}/{cc} {d}/{d}\nf {a}/{a} {d}/{d} {b}/{b}");
        }
    }
    s
}

/// Box OBJ with 8 shared corners (so smooth normals would be wrong: tests the crease logic).
fn box_obj(lo: Vec3, hi: Vec3) -> String {
    let mut s = String::new();
    for k in 0..8 {
        let p = Vec3::new(
            if k & 1 == 0 { lo.x } else { hi.x },
            if k & 2 == 0 { lo.y } else { hi.y },
            if k & 4 == 0 { lo.z } else { hi.z },
        );
        s += &format!("v {} {} {}\n", p.x, p.y, p.z);
    }
    // Outward CCW quads (1-based): -x, +x, -y, +y, -z, +z.
    for q in [[1, 5, 7, 3], [2, 4, 8, 6], [1, 2, 6, 5], [3, 7, 8, 4], [1, 3, 4, 2], [5, 6, 8, 7]] {
        s += &format!("f {} {} {} {}\n", q[0], q[1], q[2], q[3]);
    }
    s
}

fn identity_smpl() -> SmplParams {
    SmplParams::from_body(&BodyParams::default(), 1.0)
}

fn render(scan: &Scan, smpl: &SmplParams, cam: &OrbitCamera, size: usize) -> RenderedViews {
    render_scan(scan, &RenderableScan::new(scan, smpl), cam, size, 2)
}

/// World ray through the centre of pixel (x, y).
fn pixel_ray(cam: &OrbitCamera, x: usize, y: usize, size: usize) -> (Vec3, Vec3) {
    let t = (cam.fov_y / 2.0).tan();
    let nx = ((x as f32 + 0.5) / size as f32 * 2.0 - 1.0) * t;
    let ny = (1.0 - (y as f32 + 0.5) / size as f32 * 2.0) * t;
    let inv = cam.world_to_camera().inverse();
    (cam.eye(), inv.transform_vector3(Vec3::new(nx, ny, -1.0)).normalize())
}

/// The fully covered pixels of a `size`² mask: their index and the camera ray through them.
fn covered_rays<'a>(
    mask: &'a [u8],
    cam: &'a OrbitCamera,
    size: usize,
) -> impl Iterator<Item = (usize, (Vec3, Vec3))> + 'a {
    (0..size * size).filter(|&k| mask[k] == 255).map(move |k| (k, pixel_ray(cam, k % size, k / size, size)))
}

fn decode_normal(v: &RenderedViews, k: usize) -> Vec3 {
    Vec3::new(v.normal[3 * k] as f32, v.normal[3 * k + 1] as f32, v.normal[3 * k + 2] as f32) / 127.5 - Vec3::ONE
}

fn angle_deg(a: Vec3, b: Vec3) -> f32 {
    a.normalize().dot(b.normalize()).clamp(-1.0, 1.0).acos().to_degrees()
}

#[test]
fn sphere_scan_normals_mask_area_and_texture_match_the_analytic_sphere() {
    let (c, r) = (Vec3::new(0.05, -0.1, 0.02), 0.45);
    let mesh = parse_obj(&uv_sphere_obj(c, r, 160, 80)).unwrap();
    // Texture: left half red, right half blue (u < 0.5 ⇔ longitude in [0, π)).
    let px: Vec<u8> = (0..256).flat_map(|i| if i < 128 { [255, 0, 0] } else { [0, 0, 255] }).collect();
    let scan =
        Scan { mesh, textures: vec![Some(Texture::from_srgb8(256, 1, 3, &px).unwrap())], colors: vec![Vec3::ONE] };
    let cam = OrbitCamera { yaw: 0.8, pitch: 0.15, target: c, ..OrbitCamera::default() };
    let size = 256;
    let v = render(&scan, &identity_smpl(), &cam, size);

    // Mask area vs the projected disc: angular radius asin(r/d), image radius tan(α)/tan(fov/2)·size/2.
    let d = cam.radius;
    let rad = (r / d).asin().tan() / (reference_fov_y() / 2.0).tan() * size as f32 / 2.0;
    let want = std::f32::consts::PI * rad * rad;
    let got = v.mask.iter().map(|&m| m as f32 / 255.0).sum::<f32>();
    assert!((got / want - 1.0).abs() < 0.01, "mask area {got} vs projected {want}");

    // Normals vs the analytic normal at the ray's hit; colours vs the texture half.
    let (mut sum, mut n, mut worst) = (0.0f32, 0, 0.0f32);
    let (mut colour_ok, mut colour_n) = (0, 0);
    for (k, (o, dir)) in covered_rays(&v.mask, &cam, size) {
        let oc = o - c;
        let b = oc.dot(dir);
        let disc = b * b - (oc.length_squared() - r * r);
        if disc < 0.0 {
            continue;
        }
        let hit = o + dir * (-b - disc.sqrt());
        let nrm = (hit - c) / r;
        let e = angle_deg(decode_normal(&v, k), nrm);
        sum += e;
        worst = worst.max(e);
        n += 1;
        // Longitude of the hit: atan2(x, z) in [0, 2π); stay away from the seams.
        let lon = nrm.x.atan2(nrm.z).rem_euclid(std::f32::consts::TAU);
        let margin = 0.1;
        let red = lon > margin && lon < std::f32::consts::PI - margin;
        let blue = lon > std::f32::consts::PI + margin && lon < std::f32::consts::TAU - margin;
        if red || blue {
            colour_n += 1;
            let p = &v.rgb[3 * k..3 * k + 3];
            let ok = if red { p[0] >= 250 && p[2] <= 5 } else { p[2] >= 250 && p[0] <= 5 };
            colour_ok += ok as usize;
        }
    }
    let mean = sum / n as f32;
    assert!(n > 8000, "{n} interior pixels");
    assert!(mean < 2.0, "mean normal error {mean:.3}°");
    assert!(worst < 6.0, "worst normal error {worst:.3}°");
    assert!(colour_ok as f32 > 0.995 * colour_n as f32, "{colour_ok}/{colour_n} texels have the texture's colour");
    // Background: white RGB, mid-grey normals, zero mask.
    assert_eq!(&v.rgb[..3], &[255, 255, 255]);
    assert_eq!(&v.normal[..3], &[128, 128, 128]);
    assert_eq!(v.mask[0], 0);
}

/// Area of the convex hull of 2D points (monotone chain).
fn hull_area(mut p: Vec<Vec2>) -> f32 {
    p.sort_by(|a, b| a.x.partial_cmp(&b.x).unwrap().then(a.y.partial_cmp(&b.y).unwrap()));
    let cross = |o: Vec2, a: Vec2, b: Vec2| (a - o).perp_dot(b - o);
    let mut h: Vec<Vec2> = Vec::new();
    for pass in 0..2 {
        let start = h.len();
        let it: Box<dyn Iterator<Item = &Vec2>> = if pass == 0 { Box::new(p.iter()) } else { Box::new(p.iter().rev()) };
        for &q in it {
            while h.len() >= start + 2 && cross(h[h.len() - 2], h[h.len() - 1], q) <= 0.0 {
                h.pop();
            }
            h.push(q);
        }
        h.pop();
    }
    let n = h.len();
    (0..n).map(|i| h[i].perp_dot(h[(i + 1) % n])).sum::<f32>().abs() / 2.0
}

#[test]
fn box_scan_is_flat_shaded_and_covers_its_projected_hull() {
    let (lo, hi) = (Vec3::new(-0.3, -0.4, -0.2), Vec3::new(0.25, 0.1, 0.3));
    // The scan is stored scaled and translated; smpl.json maps it back (x / scale − transl).
    let smpl = SmplParams { scale: 1.25, transl: vec![0.1, -0.05, 0.0], ..identity_smpl() };
    let t = smpl.translation();
    let mesh = parse_obj(&box_obj((lo + t) * 1.25, (hi + t) * 1.25)).unwrap();
    let scan = Scan { mesh, textures: vec![None], colors: vec![Vec3::new(0.2, 0.6, 0.4)] };
    let cam = OrbitCamera { yaw: 0.6, pitch: 0.3, target: (lo + hi) / 2.0, ..OrbitCamera::default() };
    let size = 256;
    let v = render(&scan, &smpl, &cam, size);

    let vp = cam.projection_gl(1.0) * cam.world_to_camera();
    let corners: Vec<Vec2> = (0..8)
        .map(|k| {
            let p = Vec3::new(
                if k & 1 == 0 { lo.x } else { hi.x },
                if k & 2 == 0 { lo.y } else { hi.y },
                if k & 4 == 0 { lo.z } else { hi.z },
            );
            let q = vp * p.extend(1.0);
            Vec2::new((q.x / q.w + 1.0) * 0.5 * size as f32, (1.0 - q.y / q.w) * 0.5 * size as f32)
        })
        .collect();
    let want = hull_area(corners);
    let got = v.mask.iter().map(|&m| m as f32 / 255.0).sum::<f32>();
    assert!((got / want - 1.0).abs() < 0.01, "mask area {got} vs projected hull {want}");

    // Every fully covered pixel's normal is the analytic face normal of the ray's hit.
    let (mut sum, mut n) = (0.0f32, 0);
    for (k, (o, d)) in covered_rays(&v.mask, &cam, size) {
        // Slab test: the entry face is the axis of the largest t_near.
        let (t0, t1) = ((lo - o) / d, (hi - o) / d);
        let near = t0.min(t1);
        let axis = if near.x >= near.y && near.x >= near.z {
            0
        } else if near.y >= near.z {
            1
        } else {
            2
        };
        let mut nrm = Vec3::ZERO;
        nrm[axis] = -d[axis].signum();
        sum += angle_deg(decode_normal(&v, k), nrm);
        n += 1;
    }
    let mean = sum / n as f32;
    assert!(n > 3000, "{n}");
    assert!(mean < 2.0, "mean normal error {mean:.3}° (shared corners must not smooth the faces)");
    // Untextured material: the Kd colour, sRGB-encoded.
    let centre = (size / 2) * size + size / 2;
    let want = getavatar_core::render::colour::linear_to_srgb(Vec3::new(0.2, 0.6, 0.4)) * 255.0;
    let p = &v.rgb[3 * centre..3 * centre + 3];
    assert!((p[1] as f32 - want.y).abs() <= 1.0, "{p:?} vs {want}");
}

#[test]
fn camera_protocol_statistics_over_1000_draws() {
    let mut rng = Rng::new(42, 7);
    let cams: Vec<OrbitCamera> = (0..1000).map(|_| sample_data_camera(&mut rng, -0.2)).collect();
    // Azimuth uniform in [0, 2π): Kolmogorov–Smirnov distance below the 1 % critical value 1.63/√n.
    let mut az: Vec<f32> = cams.iter().map(|c| c.yaw / std::f32::consts::TAU).collect();
    assert!(az.iter().all(|a| (0.0..1.0).contains(a)));
    az.sort_by(|a, b| a.partial_cmp(b).unwrap());
    let n = az.len() as f32;
    let ks = az
        .iter()
        .enumerate()
        .map(|(i, a)| ((i + 1) as f32 / n - a).abs().max((a - i as f32 / n).abs()))
        .fold(0.0, f32::max);
    assert!(ks < 1.63 / n.sqrt(), "KS distance {ks}");
    // Elevation ~ N(0, 0.1): mean ≈ 0, std ≈ 0.1.
    let el: Vec<f32> = cams.iter().map(|c| c.pitch).collect();
    let mean = el.iter().sum::<f32>() / n;
    let std = (el.iter().map(|e| (e - mean).powi(2)).sum::<f32>() / n).sqrt();
    assert!(mean.abs() < 0.01, "elevation mean {mean}");
    assert!((std / DATA_ELEVATION_STD - 1.0).abs() < 0.07, "elevation std {std}");
    // Radius, fov and look-at follow the protocol.
    for c in &cams {
        assert!((c.eye() - c.target).length() - 2.3 < 1e-5);
        assert_eq!(c.target, Vec3::new(0.0, -0.2, 0.0));
        assert!((c.fov_y.to_degrees() - 49.134).abs() < 1e-2);
    }
}

#[test]
fn dataset_reader_validates_images_and_names_bad_files() {
    let dir = std::env::temp_dir().join(format!("getavatar-dataset-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(dir.join("s")).unwrap();
    let label = Label::new(OrbitCamera::default().world_to_camera(), &BodyParams::default());
    let entries = vec![("s/000.png".to_string(), label.clone()), ("s/001.png".to_string(), label)];
    std::fs::write(dir.join("dataset.json"), labels_to_json(&entries)).unwrap();
    let rgba: Vec<u8> = (0..8 * 8).flat_map(|i| [i as u8, 10, 20, if i % 2 == 0 { 255 } else { 0 }]).collect();
    let normal = vec![128u8; 8 * 8 * 3];
    for v in ["000", "001"] {
        std::fs::write(dir.join(format!("s/{v}.png")), encode_png(8, 8, 4, &rgba).unwrap()).unwrap();
    }
    // RGB-only datasets (no normal maps at all) are valid.
    let ds = Dataset::open(&dir).unwrap();
    assert_eq!((ds.len(), ds.resolution, ds.has_normals), (2, 8, false));
    let s = ds.load(1).unwrap();
    assert_eq!(s.mask[0], 1.0);
    assert_eq!(s.mask[1], 0.0);
    assert!((s.rgb[3] - 1.0 / 255.0).abs() < 1e-6);
    // Normal maps for some images but not all: the missing one is named.
    std::fs::write(dir.join("s/000_normal.png"), encode_png(8, 8, 3, &normal).unwrap()).unwrap();
    let e = Dataset::open(&dir).unwrap_err().to_string();
    assert!(e.contains("s/001_normal.png") && e.contains("missing"), "{e}");
    std::fs::write(dir.join("s/001_normal.png"), encode_png(8, 8, 3, &normal).unwrap()).unwrap();
    let ds = Dataset::open(&dir).unwrap();
    assert!(ds.has_normals);
    assert!(ds.load(0).unwrap().normal.unwrap().iter().all(|x| x.abs() < 0.01));
    // A wrongly sized image is named when loaded; an RGB image without alpha too.
    std::fs::write(dir.join("s/001.png"), encode_png(4, 4, 4, &rgba[..64]).unwrap()).unwrap();
    let e = ds.load(1).unwrap_err().to_string();
    assert!(e.contains("001.png") && e.contains("4×4, expected 8×8"), "{e}");
    std::fs::write(dir.join("s/001.png"), encode_png(8, 8, 3, &normal).unwrap()).unwrap();
    let e = ds.load(1).unwrap_err().to_string();
    assert!(e.contains("no alpha channel"), "{e}");
    // A label with a wrong float count is rejected naming the entry.
    let mut bad =
        serde_json::from_str::<serde_json::Value>(&std::fs::read_to_string(dir.join("dataset.json")).unwrap()).unwrap();
    bad["labels"]["s/001.png"].as_array_mut().unwrap().truncate(72);
    std::fs::write(dir.join("dataset.json"), bad.to_string()).unwrap();
    let e = Dataset::open(&dir).unwrap_err().to_string();
    assert!(e.contains("s/001.png") && e.contains("72 numbers, expected 98"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

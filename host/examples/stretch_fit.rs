// Scratch: the stretch the counts miss on a clean independent device, from
// the simulator's truths, and which terms represent it (T l, T alone: the
// lead, per-string constants: the home capture), and how much of a shared
// sag it makes.
//
// `cargo run --release -p spidar --example stretch_fit -- SEED`
//
// Per row and string (abnormal rows skipped):
// - `stretch` = (G - U) - (G_home - U_home): what the counts miss of the
//   stretch (the truths' geometric and natural lengths, the home state of
//   the string at the home tension);
// - `total` = |p - e_home| - |home - e_home| - (U - U_home): the whole
//   model-side residual with an ideal winding law (e_home: the string's exit
//   point at home, fixed), i.e. stretch, arc, sag, guide travel and flex.
// Each is regressed on the linearized geometry (home, anchors, tracker,
// winding radius per string, a shared theta^2) plus candidate columns.
use nalgebra::{DMatrix, DVector};
use spidar::sim::physics::{self, PhysicsConfig, PhysicsDevice};
use spidar::sim::SessionKind;

fn lsq(rows: &[Vec<f64>], y: &[f64]) -> Vec<f64> {
    let n = rows[0].len();
    let a = DMatrix::from_fn(rows.len(), n, |r, c| rows[r][c]);
    let b = DVector::from_column_slice(y);
    let svd = a.svd(true, true);
    svd.solve(&b, 1e-10).unwrap().iter().cloned().collect()
}

fn rms_of(rows: &[Vec<f64>], y: &[f64], b: &[f64]) -> f64 {
    (rows
        .iter()
        .zip(y)
        .map(|(r, y)| {
            let f: f64 = r.iter().zip(b).map(|(a, b)| a * b).sum();
            (y - f).powi(2)
        })
        .sum::<f64>()
        / y.len() as f64)
        .sqrt()
}

fn norm(d: [f64; 3]) -> f64 {
    (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
}

fn main() {
    let seed: u64 = std::env::args()
        .nth(1)
        .map(|s| s.parse().unwrap())
        .unwrap_or(1);
    let c = PhysicsConfig::default();
    let device = PhysicsDevice::new(&c, seed).unwrap();
    let (train, truths) =
        physics::simulate_session(&device, SessionKind::Lattice, seed + 1).unwrap();
    let n = device.string_count();
    let th = device.home_tension_n;
    let home: Vec<_> = (0..n)
        .map(|i| {
            device
                .natural_length(i, &device.home_mm, th, th * n as f64, 0.0)
                .unwrap()
        })
        .collect();
    println!("seed {seed}: {n} strings, home tension {th:.3} N");
    for i in 0..n {
        let s = &device.strings[i];
        println!(
            "  string {i}: EA {:.0} N (1/EA {:.2e}) lead {:.0} mm arc_home {:.1} free_home {:.0} mass {:.2} g/m  home stretch (G-U) {:.3} mm",
            s.stiffness_n,
            1.0 / s.stiffness_n,
            s.lead_mm,
            home[i].path.length_mm - home[i].path.free_mm,
            home[i].path.free_mm,
            s.mass_g_per_m,
            home[i].geometric_mm - home[i].natural_mm
        );
    }
    // Columns.
    let nh = 3;
    let na = 3 * n;
    let nt = 6;
    let nr = n;
    let nk = 1;
    let ngeo = nh + na + nt + nr + nk;
    // Candidate columns (after geometry), named.
    let cand_names = [
        "T l", "T", "1", "l_home", "-v (sag)", "v_home", // shared
    ];
    let ncs = cand_names.len();
    // Per-string candidates: T l_i, T_i, 1_i.
    let total = ngeo + ncs + 3 * n;
    let mut rows = Vec::new();
    let mut y_stretch = Vec::new();
    let mut y_total = Vec::new();
    let mut y_k = Vec::new(); // stretch per string at its own 1/EA: (T (l + lead + arc) - Th (...))/EA
    for (t, s) in truths.iter().zip(&train.samples) {
        if t.abnormal || s.tracker.is_none() {
            continue;
        }
        let p = t.meeting_mm;
        let tension = s.tension_n.unwrap();
        let mut bad = false;
        let mut row_set = Vec::new();
        for i in 0..n {
            let e = home[i].path.exit_mm;
            let dp = [p[0] - e[0], p[1] - e[1], p[2] - e[2]];
            let lp = norm(dp);
            let up = dp.map(|x| x / lp);
            let h = device.home_mm;
            let dh = [h[0] - e[0], h[1] - e[1], h[2] - e[2]];
            let lh = norm(dh);
            let uh = dh.map(|x| x / lh);
            let payout = t.natural_mm[i] - home[i].natural_mm;
            let stretch =
                (t.geometric_mm[i] - t.natural_mm[i]) - (home[i].geometric_mm - home[i].natural_mm);
            let tot = lp - lh - payout;
            if tot.abs() > 25.0 {
                bad = true;
            }
            let mut row = vec![0.0; total];
            let mut col = 0;
            for c in 0..3 {
                row[col + c] = -uh[c];
            }
            col += nh;
            for c in 0..3 {
                row[col + 3 * i + c] = -up[c] + uh[c];
            }
            col += na;
            for c in 0..3 {
                row[col + c] = -up[c];
            }
            let pu = [
                p[1] * up[2] - p[2] * up[1],
                p[2] * up[0] - p[0] * up[2],
                p[0] * up[1] - p[1] * up[0],
            ];
            for c in 0..3 {
                row[col + 3 + c] = pu[c];
            }
            col += nt;
            let theta = std::f64::consts::TAU * s.counts[i] as f64
                / device.nominal.counts_per_rev[i] as f64;
            row[col + i] = -theta;
            col += nr;
            row[col] = theta * theta;
            col += nk;
            // Candidates, with the model's variables: l = home_length + payout.
            let tt = tension[i];
            let l = lh + payout;
            let cos2 = (dp[0] * dp[0] + dp[1] * dp[1]) / (lp * lp);
            let cos2h = (dh[0] * dh[0] + dh[1] * dh[1]) / (lh * lh);
            let lm = l / 1000.0;
            let v = cos2 * lm * lm * lm / (tt.max(0.25) * tt.max(0.25));
            let vh = cos2h * (lh / 1000.0).powi(3);
            let cand = [tt * l, tt, 1.0, lh, -v, vh];
            for (k, x) in cand.iter().enumerate() {
                row[col + k] = *x;
            }
            col += ncs;
            row[col + 3 * i] = tt * l;
            row[col + 3 * i + 1] = tt;
            row[col + 3 * i + 2] = 1.0;
            let st = &device.strings[i];
            let arc = t.geometric_mm[i]
                - t.free_mm[i]
                - st.lead_mm
                - (t.geometric_mm[i] - t.natural_mm[i]) * 0.0;
            let _ = arc;
            y_k.push(stretch);
            row_set.push((row, stretch, tot));
        }
        if bad {
            continue;
        }
        for (row, st, tot) in row_set {
            rows.push(row);
            y_stretch.push(st);
            y_total.push(tot);
        }
    }
    let m = rows.len();
    let mean_abs = y_stretch.iter().map(|x| x.abs()).sum::<f64>() / m as f64;
    let rms = (y_stretch.iter().map(|x| x * x).sum::<f64>() / m as f64).sqrt();
    let mx = y_stretch.iter().cloned().fold(f64::MIN, f64::max);
    let mn = y_stretch.iter().cloned().fold(f64::MAX, f64::min);
    println!("{m} residuals; stretch missed: mean |.| {mean_abs:.3} rms {rms:.3} range {mn:.3}..{mx:.3} mm");
    let geo: Vec<usize> = (0..ngeo).collect();
    let c0 = ngeo;
    let cps = ngeo + ncs;
    let sets: Vec<(&str, Vec<usize>)> = vec![
        ("geometry", geo.clone()),
        (
            "geo + sag(c,h)",
            [geo.clone(), vec![c0 + 4, c0 + 5]].concat(),
        ),
        ("geo + T l", [geo.clone(), vec![c0]].concat()),
        (
            "geo + T l + sag",
            [geo.clone(), vec![c0, c0 + 4, c0 + 5]].concat(),
        ),
        ("geo + T l, T", [geo.clone(), vec![c0, c0 + 1]].concat()),
        (
            "geo + T l, T, 1",
            [geo.clone(), vec![c0, c0 + 1, c0 + 2]].concat(),
        ),
        (
            "geo + T l, T, 1, l_home",
            [geo.clone(), vec![c0, c0 + 1, c0 + 2, c0 + 3]].concat(),
        ),
        (
            "geo + T l, T, + sag",
            [geo.clone(), vec![c0, c0 + 1, c0 + 4, c0 + 5]].concat(),
        ),
        (
            "geo + T l, T, 1 + sag",
            [geo.clone(), vec![c0, c0 + 1, c0 + 2, c0 + 4, c0 + 5]].concat(),
        ),
        (
            "geo + per-string T l_i",
            [geo.clone(), (0..n).map(|i| cps + 3 * i).collect()].concat(),
        ),
        (
            "geo + per-string T l_i + sag",
            [
                geo.clone(),
                (0..n).map(|i| cps + 3 * i).collect(),
                vec![c0 + 4, c0 + 5],
            ]
            .concat(),
        ),
        (
            "geo + per-string T l_i, T_i",
            [
                geo.clone(),
                (0..n)
                    .flat_map(|i| [cps + 3 * i, cps + 3 * i + 1])
                    .collect(),
            ]
            .concat(),
        ),
        (
            "geo + per-string T l_i, T_i, 1_i",
            [geo.clone(), (cps..total).collect()].concat(),
        ),
        (
            "geo + per-string T l_i, T_i, 1_i + sag",
            [geo.clone(), (cps..total).collect(), vec![c0 + 4, c0 + 5]].concat(),
        ),
        ("no geometry: T l", vec![c0]),
        ("no geometry: T l, T", vec![c0, c0 + 1]),
        ("no geometry: T l, T, 1", vec![c0, c0 + 1, c0 + 2]),
        ("no geometry: per-string", (cps..total).collect()),
    ];
    for (yname, y) in [("stretch", &y_stretch), ("total", &y_total)] {
        println!("--- y = {yname}");
        for (name, cols) in &sets {
            let rr: Vec<Vec<f64>> = rows
                .iter()
                .map(|r| cols.iter().map(|&c| r[c]).collect())
                .collect();
            let b = lsq(&rr, y);
            let r = rms_of(&rr, y, &b);
            let mut shown = Vec::new();
            for (k, &c) in cols.iter().enumerate() {
                if (c0..cps).contains(&c) {
                    shown.push(format!("{}={:.3e}", cand_names[c - c0], b[k]));
                }
            }
            let per: Vec<String> = cols
                .iter()
                .enumerate()
                .filter(|(_, &c)| c >= cps && (c - cps) % 3 == 0)
                .map(|(k, _)| format!("{:.2e}", b[k]))
                .collect();
            let per_t: Vec<String> = cols
                .iter()
                .enumerate()
                .filter(|(_, &c)| c >= cps && (c - cps) % 3 == 1)
                .map(|(k, &c)| {
                    // lead estimate = b(T_i) / b(T l_i)
                    let kl = cols
                        .iter()
                        .position(|&d| d == c - 1)
                        .map(|j| b[j])
                        .unwrap_or(f64::NAN);
                    format!("{:.0}", b[k] / kl)
                })
                .collect();
            println!(
                "{name:42} rms {r:.4}  {}{}{}",
                shown.join(" "),
                if per.is_empty() {
                    String::new()
                } else {
                    format!(" k_i [{}]", per.join(" "))
                },
                if per_t.is_empty() {
                    String::new()
                } else {
                    format!(" lead_i [{}]", per_t.join(" "))
                }
            );
        }
    }
}

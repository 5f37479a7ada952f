//! The command line.

use super::runs::Run;

/// What the command line asked for.
pub(super) struct Options {
    pub(super) seeds: u64,
    pub(super) quick: bool,
    pub(super) analysis: bool,
    /// `--only=independent:slip,model:clean`: just these cases.
    only: Option<Vec<String>>,
    pub(super) ablation: bool,
    /// `--no-forward`: drifts judged on the blocked folds alone (to
    /// measure what forward chaining does).
    pub(super) no_forward: bool,
    /// `--write=DIR`: each case's geometry and sessions written to
    /// `DIR/SIM-EFFECT-SEED/`, for `spidar calibrate` to reproduce a row.
    write: Option<std::path::PathBuf>,
}

impl Options {
    pub(super) fn parse() -> Options {
        let mut o = Options {
            seeds: 3,
            quick: false,
            analysis: true,
            only: None,
            ablation: false,
            no_forward: false,
            write: None,
        };
        for a in std::env::args().skip(1) {
            if let Some(list) = a.strip_prefix("--only=") {
                o.only = Some(list.split(',').map(str::to_string).collect());
                continue;
            }
            if let Some(dir) = a.strip_prefix("--write=") {
                o.write = Some(dir.into());
                continue;
            }
            match a.as_str() {
                "--quick" => o.quick = true,
                "--no-analysis" => o.analysis = false,
                "--ablation" => o.ablation = true,
                "--no-forward" => o.no_forward = true,
                s => {
                    o.seeds = s.parse().expect(
                        "usage: physics_bench [SEEDS] [--quick] [--no-analysis] [--no-forward] \
                     [--only=SIM:EFFECT,..] [--write=DIR]",
                    )
                }
            }
        }
        o
    }

    /// Writes `run`'s geometry and sessions to `--write`'s
    /// `DIR/SIMULATOR-EFFECT-SEED/` (`geometry.toml`, `train.csv`,
    /// `test.csv`), when asked for.
    pub(super) fn write_run(&self, simulator: &str, effect: &str, seed: u64, run: &Run) {
        let Some(dir) = &self.write else { return };
        let dir = dir.join(format!("{simulator}-{effect}-{seed}"));
        std::fs::create_dir_all(&dir).expect("--write: the case's folder");
        run.geometry
            .write(dir.join("geometry.toml"))
            .expect("--write: geometry");
        run.train
            .write(dir.join("train.csv"))
            .expect("--write: training session");
        run.test
            .write(dir.join("test.csv"))
            .expect("--write: test session");
    }

    /// Whether the case `simulator:effect` is to run.
    pub(super) fn wanted(&self, simulator: &str, effect: Option<&str>) -> bool {
        self.only.as_ref().is_none_or(|o| {
            o.iter()
                .any(|c| *c == format!("{simulator}:{}", effect.unwrap_or("clean")))
        })
    }
}

//! `loopd calibrate`: fits the loop confidence of one model's descriptors on the candidates that
//! `loopd eval --samples-out` wrote for training sets, and keeps it in a calibration file beside
//! the calibrators of other models.
use super::ModelArgs;
use crate::model::network::Variant;
use crate::verify::confidence::{CalibrationFile, Calibrator, Sample, FEATURE_NAMES};
use anyhow::{Context, Result};
use clap::Args;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Args)]
pub struct CalibrateArgs {
    /// The model whose descriptors the samples are of (its descriptor id names the calibrator).
    #[command(flatten)]
    pub model: ModelArgs,
    /// A training set's samples: NAME=FILE (JSON lines from `loopd eval --samples-out`); repeat.
    #[arg(long = "samples", required = true, value_parser = parse_named)]
    pub samples: Vec<(String, PathBuf)>,
    /// The calibration file to write; the calibrators of other models it holds are kept.
    #[arg(long, default_value = crate::verify::confidence::SHIPPED)]
    pub out: PathBuf,
}

fn parse_named(s: &str) -> Result<(String, PathBuf), String> {
    let (name, path) = s.split_once('=').ok_or_else(|| format!("expected NAME=FILE, got '{s}'"))?;
    Ok((name.to_string(), PathBuf::from(path)))
}

pub fn run(a: CalibrateArgs) -> Result<ExitCode> {
    let mut model = a.model.clone();
    // Only the descriptor id is needed: no forward pass runs.
    model.device = "cpu".into();
    let descriptor_id = model.load()?.descriptor_id(Variant::FULL);
    let mut samples = Vec::new();
    let mut names = Vec::new();
    for (name, path) in &a.samples {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let before = samples.len();
        for (n, line) in text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty()) {
            let s: Sample = serde_json::from_str(line).with_context(|| format!("{}:{}", path.display(), n + 1))?;
            samples.push(s);
        }
        let got = &samples[before..];
        println!(
            "{name}: {} candidates, {} true, {} first candidates ({} true)",
            got.len(),
            got.iter().filter(|s| s.truth).count(),
            got.iter().filter(|s| s.best).count(),
            got.iter().filter(|s| s.best && s.truth).count()
        );
        names.push(name.clone());
    }
    let c = Calibrator::fit(&descriptor_id, &samples, names).map_err(anyhow::Error::msg)?;
    for (name, w) in FEATURE_NAMES.iter().zip(&c.weights) {
        println!("  {name:<28} {w:+.4}");
    }
    println!("  {:<28} {:+.4}", "bias", c.bias);
    println!("{descriptor_id}: loop confidence {:.2} ({} samples, {} true)", c.loop_confidence, c.samples, c.positives);
    let file = match a.out.exists() {
        true => CalibrationFile::read(&a.out)?,
        false => CalibrationFile::default(),
    };
    let file = file.with(c);
    std::fs::write(&a.out, serde_json::to_string_pretty(&file)? + "\n")
        .with_context(|| format!("writing {}", a.out.display()))?;
    println!("written: {}", a.out.display());
    Ok(ExitCode::SUCCESS)
}

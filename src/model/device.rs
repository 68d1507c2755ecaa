//! Device and precision selection.
use anyhow::{bail, Result};
use tch::{Device, Kind};

/// `auto` (CUDA when present), `cpu`, `cuda` or `cuda:N`.
pub fn parse_device(s: &str) -> Result<Device> {
    match s {
        "auto" => Ok(Device::cuda_if_available()),
        "cpu" => Ok(Device::Cpu),
        "cuda" => cuda(0),
        _ => match s.strip_prefix("cuda:").map(str::parse::<usize>) {
            Some(Ok(n)) => cuda(n),
            _ => bail!("unknown device '{s}': expected auto, cpu, cuda or cuda:N"),
        },
    }
}

fn cuda(n: usize) -> Result<Device> {
    let count = tch::Cuda::device_count() as usize;
    if n >= count {
        bail!("device cuda:{n} requested but {count} CUDA device(s) are available");
    }
    Ok(Device::Cuda(n))
}

/// Weight and activation precision.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum DType {
    F32,
    F16,
    Bf16,
}

impl DType {
    pub fn kind(self) -> Kind {
        match self {
            DType::F32 => Kind::Float,
            DType::F16 => Kind::Half,
            DType::Bf16 => Kind::BFloat16,
        }
    }

    /// Half precision convolutions on CPU are slow or missing in libtorch: CUDA only.
    pub fn check(self, device: Device) -> Result<()> {
        if self != DType::F32 && device == Device::Cpu {
            bail!("--dtype {self:?} needs a CUDA device; use f32 on CPU");
        }
        Ok(())
    }
}

pub fn device_name(d: Device) -> String {
    match d {
        Device::Cpu => "cpu".into(),
        Device::Cuda(n) => format!("cuda:{n}"),
        other => format!("{other:?}").to_lowercase(),
    }
}

// libtorch's own setter of the autocast precision (ATen/autocast_mode.h), which tch does not wrap:
// `void at::autocast::set_autocast_dtype(c10::DeviceType, c10::ScalarType)`, a free function (C
// calling convention on x86-64 and aarch64 Linux) whose two enums are `int8_t`
// (c10/core/DeviceType.h, c10/core/ScalarType.h). It is exported by libtorch_cpu, which tch links.
extern "C" {
    #[link_name = "_ZN2at8autocast18set_autocast_dtypeEN3c1010DeviceTypeENS1_10ScalarTypeE"]
    fn at_autocast_set_autocast_dtype(device_type: i8, dtype: i8);
}

/// c10::DeviceType::CUDA.
const C10_CUDA: i8 = 1;

/// Runs `f` under libtorch's CUDA autocast in `dtype`: convolutions and matrix products in half
/// precision, reductions, normalisations and losses in f32 (PyTorch's
/// `torch.autocast("cuda", dtype)`). F32 runs `f` as it is.
pub fn autocast<T>(dtype: DType, f: impl FnOnce() -> T) -> T {
    let code: i8 = match dtype {
        DType::F32 => return f(),
        DType::F16 => 5,   // c10::ScalarType::Half
        DType::Bf16 => 15, // c10::ScalarType::BFloat16
    };
    // SAFETY: the declaration above matches the exported C++ function (both arguments are
    // `int8_t` enums passed by value, no return value); the values are valid enumerators, and the
    // setter only stores them in libtorch's autocast state, which tch::autocast then enables.
    unsafe { at_autocast_set_autocast_dtype(C10_CUDA, code) };
    tch::autocast(true, f)
}

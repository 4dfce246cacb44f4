//! `--backend`: the device a command computes on, and the adapter it found.
//!
//! `ndarray` is the CPU. `wgpu` is burn's wgpu runtime on the machine's native graphics API
//! (Vulkan on Linux, Metal on macOS, DX12 on Windows). The adapter is printed when it is
//! opened, so a figure measured on a software adapter (Mesa's lavapipe or llvmpipe, which
//! emulate a GPU on the CPU) is never taken for a GPU figure.

use anyhow::{anyhow, bail, Result};
use getavatar_core::burn::tensor::Device;

/// The `--backend` argument of every command that computes.
#[derive(clap::Args, Clone, Debug)]
pub struct BackendArg {
    /// ndarray (CPU) or wgpu (the machine's GPU through Vulkan, Metal or DX12; Mesa's
    /// lavapipe without one). The adapter is printed at start.
    #[arg(long, default_value = "ndarray", value_parser = ["ndarray", "wgpu"])]
    pub backend: String,
}

impl BackendArg {
    pub fn device(&self) -> Result<Device> {
        device_for(&self.backend)
    }
}

/// What the wgpu runtime opened: enough to tell a real GPU from an emulated one.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Adapter {
    pub name: String,
    pub driver: String,
    /// wgpu's device type: DiscreteGpu, IntegratedGpu, VirtualGpu, Cpu or Other.
    pub kind: String,
    /// The graphics API: Vulkan, Metal, Dx12, …
    pub api: String,
}

impl Adapter {
    /// A software rasteriser (lavapipe, llvmpipe, SwiftShader, WARP): its "GPU" figures are
    /// CPU figures.
    pub fn is_software(&self) -> bool {
        let name = self.name.to_lowercase();
        self.kind == "Cpu" || ["llvmpipe", "lavapipe", "swiftshader", "warp"].iter().any(|s| name.contains(s))
    }

    /// One line for logs and benchmark headers.
    pub fn describe(&self) -> String {
        let warning = if self.is_software() {
            " — a SOFTWARE adapter that emulates a GPU on the CPU: these are not GPU figures"
        } else {
            ""
        };
        format!("{} (driver {}, {}, {}){warning}", self.name, self.driver, self.kind, self.api)
    }
}

thread_local! {
    static OPENED: std::cell::RefCell<Option<Adapter>> = const { std::cell::RefCell::new(None) };
}

/// The adapter the last `device_for("wgpu")` opened on this thread, if any.
pub fn opened_adapter() -> Option<Adapter> {
    OPENED.with(|a| a.borrow().clone())
}

/// The device of `--backend`. Opening wgpu prints the adapter to stderr.
pub fn device_for(backend: &str) -> Result<Device> {
    Ok(match backend {
        #[allow(deprecated)]
        "ndarray" => Device::ndarray(),
        "wgpu" => {
            let (device, setup) =
                Device::wgpu_options().init_with_setup().map_err(|e| anyhow!("no wgpu adapter: {e:?}"))?;
            let info = setup.adapter.get_info();
            let driver = [info.driver.as_str(), info.driver_info.as_str()]
                .into_iter()
                .filter(|s| !s.is_empty())
                .collect::<Vec<_>>()
                .join(" ");
            let adapter = Adapter {
                name: info.name.clone(),
                driver: if driver.is_empty() { "unknown".into() } else { driver },
                kind: format!("{:?}", info.device_type),
                api: format!("{:?}", setup.backend),
            };
            eprintln!("wgpu adapter: {}", adapter.describe());
            OPENED.with(|a| *a.borrow_mut() = Some(adapter));
            device
        }
        other => bail!("unknown --backend `{other}` (ndarray, wgpu)"),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn adapter(name: &str, kind: &str) -> Adapter {
        Adapter { name: name.into(), driver: "d".into(), kind: kind.into(), api: "Vulkan".into() }
    }

    #[test]
    fn software_adapters_are_named_as_such() {
        assert!(adapter("llvmpipe (LLVM 15.0.6, 256 bits)", "Cpu").is_software());
        assert!(adapter("lavapipe", "Other").is_software());
        assert!(adapter("SwiftShader Device (Subzero)", "Cpu").is_software());
        assert!(!adapter("NVIDIA H100 80GB HBM3", "DiscreteGpu").is_software());
        assert!(adapter("llvmpipe", "Cpu").describe().contains("not GPU figures"));
        assert!(!adapter("NVIDIA H100 80GB HBM3", "DiscreteGpu").describe().contains("not GPU figures"));
    }

    #[test]
    fn an_unknown_backend_is_refused_with_the_choices() {
        let e = device_for("cuda").unwrap_err().to_string();
        assert!(e.contains("ndarray, wgpu"), "{e}");
    }
}

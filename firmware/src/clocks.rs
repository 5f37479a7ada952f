//! Clock tree.
//!
//! HSI (64 MHz, internal, so the firmware does not depend on the ST-LINK MCO
//! solder bridges) -> PLL1: /32 = 2 MHz reference, x260 = 520 MHz VCO,
//! P /1 = **520 MHz CPU**. 550 MHz needs the CPU_FREQ_BOOST option bit
//! (SYSCFG_UR18), which embassy checks; build with `--features boost-550`
//! after setting it (docs/hardware.md).
//!
//! AHB /2 = 260 (275) MHz, APB1..4 /2 = 130 (137.5) MHz; timers run at
//! 2 x APB = 260 (275) MHz. USB takes the HSI48, trimmed by the CRS from the
//! host's start-of-frame packets.

use embassy_stm32::rcc::*;
use embassy_stm32::Config;

#[cfg(not(feature = "boost-550"))]
pub const SYSCLK_HZ: u32 = 520_000_000;
#[cfg(feature = "boost-550")]
pub const SYSCLK_HZ: u32 = 550_000_000;

pub fn config() -> Config {
    let mut config = Config::default();
    let rcc = &mut config.rcc;
    rcc.hsi = Some(HSIPrescaler::DIV1);
    rcc.csi = true;
    rcc.hsi48 = Some(Hsi48Config {
        sync_from_usb: true,
    });
    rcc.pll1 = Some(Pll {
        source: PllSource::HSI,
        prediv: PllPreDiv::DIV32,
        #[cfg(not(feature = "boost-550"))]
        mul: PllMul::MUL260,
        #[cfg(feature = "boost-550")]
        mul: PllMul::MUL275,
        divp: Some(PllDiv::DIV1),
        divq: Some(PllDiv::DIV8),
        divr: None,
    });
    rcc.sys = Sysclk::PLL1_P;
    rcc.ahb_pre = AHBPrescaler::DIV2;
    rcc.apb1_pre = APBPrescaler::DIV2;
    rcc.apb2_pre = APBPrescaler::DIV2;
    rcc.apb3_pre = APBPrescaler::DIV2;
    rcc.apb4_pre = APBPrescaler::DIV2;
    rcc.voltage_scale = VoltageScale::Scale0;
    rcc.supply_config = SupplyConfig::LDO;
    rcc.mux.usbsel = mux::Usbsel::HSI48;
    // The RNG (the boot's id) runs on the HSI48 too.
    rcc.mux.rngsel = mux::Rngsel::HSI48;
    config
}

//! USB CDC-ACM link to the host.
//!
//! Bytes from the host go through a frame decoder (frames end with 0x00, as
//! COBS frames do); every complete frame goes to [`dispatch`], whose replies
//! are written back as USB packets.
//!
//! PLACEHOLDER until `spidar_protocol::frame` / `messages` land on main: the
//! decoder here only splits frames, and `dispatch` logs them and answers
//! nothing. Wiring then means: `protocol::frame::FrameDecoder::push` instead
//! of `FrameSplitter::push`, a `match` on `Request` in `dispatch` calling
//! [`Storage`] (UploadBegin/Chunk/Commit/Abort/ClearModel) and sending
//! [`crate::shared::Command`]s (Arm/Disarm/SetForceTarget/ClearFaults), and
//! `protocol::frame::encode` for the reply.

use embassy_stm32::peripherals::{PA11, PA12, USB_OTG_HS};
use embassy_stm32::usb::Driver;
use embassy_stm32::{bind_interrupts, usb, Peri};
use embassy_usb::class::cdc_acm::{CdcAcmClass, State};
use embassy_usb::driver::EndpointError;
use embassy_usb::{Builder, UsbDevice};
use static_cell::StaticCell;

use crate::storage::Storage;

bind_interrupts!(struct Irqs {
    OTG_HS => usb::InterruptHandler<USB_OTG_HS>;
});

pub type UsbDriver = Driver<'static, USB_OTG_HS>;

/// Full-speed bulk packet size.
const PACKET: u16 = 64;
/// Longest frame the link accepts (a 256-byte upload chunk plus framing).
pub const MAX_FRAME: usize = 320;

/// Builds the USB device (full speed on the OTG_HS core's internal PHY,
/// PA11/PA12 = the Nucleo's user USB connector CN13) with one CDC-ACM port.
pub fn usb(
    otg: Peri<'static, USB_OTG_HS>,
    dp: Peri<'static, PA12>,
    dm: Peri<'static, PA11>,
) -> (
    UsbDevice<'static, UsbDriver>,
    CdcAcmClass<'static, UsbDriver>,
) {
    static EP_OUT: StaticCell<[u8; 256]> = StaticCell::new();
    static CONFIG_DESC: StaticCell<[u8; 256]> = StaticCell::new();
    static BOS_DESC: StaticCell<[u8; 256]> = StaticCell::new();
    static MSOS_DESC: StaticCell<[u8; 0]> = StaticCell::new();
    static CONTROL: StaticCell<[u8; 64]> = StaticCell::new();
    static STATE: StaticCell<State> = StaticCell::new();

    let mut otg_config = usb::Config::default();
    // VBUS sensing needs PA9 and a solder bridge; the device is bus-powered
    // through the ST-LINK anyway, so treat VBUS as always present.
    otg_config.vbus_detection = false;
    let driver = Driver::new_fs(otg, Irqs, dp, dm, EP_OUT.init([0; 256]), otg_config);

    // pid.codes test VID/PID: replace with an allocated pair before shipping.
    let mut config = embassy_usb::Config::new(0x1209, 0x0001);
    config.manufacturer = Some("spidar");
    config.product = Some("SPIDAR controller (STM32H723)");
    config.serial_number = Some("0001");
    config.max_power = 100;
    config.max_packet_size_0 = 64;

    let mut builder = Builder::new(
        driver,
        config,
        CONFIG_DESC.init([0; 256]),
        BOS_DESC.init([0; 256]),
        MSOS_DESC.init([0; 0]),
        CONTROL.init([0; 64]),
    );
    let class = CdcAcmClass::new(&mut builder, STATE.init(State::new()), PACKET);
    (builder.build(), class)
}

#[embassy_executor::task]
pub async fn usb_task(mut device: UsbDevice<'static, UsbDriver>) -> ! {
    device.run().await
}

/// Splits a byte stream into 0x00-terminated frames, at most `MAX_FRAME`
/// bytes each; overlong frames are dropped up to the next 0x00. Same shape as
/// `spidar_protocol::frame::FrameDecoder::push`, which replaces it.
pub struct FrameSplitter {
    buf: [u8; MAX_FRAME],
    len: usize,
    skipping: bool,
    pub dropped: u32,
}

impl FrameSplitter {
    pub const fn new() -> Self {
        Self {
            buf: [0; MAX_FRAME],
            len: 0,
            skipping: false,
            dropped: 0,
        }
    }

    pub fn reset(&mut self) {
        self.len = 0;
        self.skipping = false;
    }

    /// Consumes input up to the end of the first frame in it; returns the
    /// bytes consumed (>= 1 for non-empty input) and the frame, if one ended.
    pub fn push(&mut self, input: &[u8]) -> (usize, Option<&[u8]>) {
        let zero = input.iter().position(|&b| b == 0);
        let segment = &input[..zero.unwrap_or(input.len())];
        let consumed = zero.map_or(input.len(), |z| z + 1);
        if self.skipping {
            self.skipping = zero.is_none();
            return (consumed, None);
        }
        if segment.len() > MAX_FRAME - self.len {
            self.dropped += 1;
            self.len = 0;
            self.skipping = zero.is_none();
            return (consumed, None);
        }
        self.buf[self.len..self.len + segment.len()].copy_from_slice(segment);
        self.len += segment.len();
        if zero.is_none() {
            return (consumed, None);
        }
        let len = core::mem::replace(&mut self.len, 0);
        if len == 0 {
            return (consumed, None);
        }
        (consumed, Some(&self.buf[..len]))
    }
}

/// Handles one frame; writes the reply frame into `out` and returns its
/// length (0 = no reply).
///
/// PLACEHOLDER: decodes nothing yet (see the module comment).
fn dispatch(frame: &[u8], _storage: &mut Storage, _out: &mut [u8]) -> usize {
    defmt::debug!(
        "link: frame of {} bytes (protocol decoding pending)",
        frame.len()
    );
    0
}

async fn send(
    class: &mut CdcAcmClass<'static, UsbDriver>,
    bytes: &[u8],
) -> Result<(), EndpointError> {
    for chunk in bytes.chunks(PACKET as usize) {
        class.write_packet(chunk).await?;
    }
    if !bytes.is_empty() && bytes.len() % PACKET as usize == 0 {
        // A full last packet: end the transfer with a zero-length packet.
        class.write_packet(&[]).await?;
    }
    Ok(())
}

#[embassy_executor::task]
pub async fn link_task(mut class: CdcAcmClass<'static, UsbDriver>, mut storage: Storage) -> ! {
    static SPLITTER: StaticCell<FrameSplitter> = StaticCell::new();
    let frames = SPLITTER.init(FrameSplitter::new());
    let mut rx = [0u8; PACKET as usize];
    let mut reply = [0u8; MAX_FRAME];
    match storage.active() {
        Some(a) => defmt::info!("link: active model {} in slot {}", a.record, a.slot),
        None => defmt::info!("link: no stored model"),
    }
    loop {
        class.wait_connection().await;
        defmt::info!("link: host connected");
        frames.reset();
        'connected: loop {
            let n = match class.read_packet(&mut rx).await {
                Ok(n) => n,
                Err(_) => break 'connected,
            };
            let mut rest = &rx[..n];
            while !rest.is_empty() {
                let (used, frame) = frames.push(rest);
                rest = &rest[used..];
                if let Some(frame) = frame {
                    let len = dispatch(frame, &mut storage, &mut reply);
                    if len > 0 && send(&mut class, &reply[..len]).await.is_err() {
                        break 'connected;
                    }
                }
            }
        }
        defmt::info!("link: host disconnected");
    }
}

//! USB CDC-ACM link to the host.
//!
//! Two tasks share the CDC-ACM class (split into receiver and sender):
//! - [`link_reader`]: bytes from the host go through
//!   `spidar_core::device::DeviceLink` (COBS frames, CRC, decoding); each
//!   request is answered by `Device::handle` under the device lock, and the
//!   encoded reply goes to the writer;
//! - [`link_writer`]: sends replies, and the state frames and events the
//!   control loop streams (with their own sequence counter).
//!
//! Everything between bytes and replies is `spidar-core`, the code the
//! virtual device runs on the host.

use embassy_futures::select::{select, Either};
use embassy_stm32::peripherals::{PA11, PA12, USB_OTG_HS};
use embassy_stm32::usb::Driver;
use embassy_stm32::{bind_interrupts, usb, Peri};
use embassy_usb::class::cdc_acm::{CdcAcmClass, Receiver, Sender, State};
use embassy_usb::driver::EndpointError;
use embassy_usb::{Builder, UsbDevice};
use static_cell::StaticCell;

use core::sync::atomic::Ordering;
use embassy_time::Instant;
use spidar_core::device::{DeviceLink, LinkCounters};
use spidar_protocol::{encode_device_message, DeviceMessage};

use crate::shared::{
    with_device, Frame, SharedDevice, StreamItem, REPLIES, STREAM, STREAM_FRAMES_SENT,
};

bind_interrupts!(struct Irqs {
    OTG_HS => usb::InterruptHandler<USB_OTG_HS>;
});

pub type UsbDriver = Driver<'static, USB_OTG_HS>;

/// Full-speed bulk packet size.
const PACKET: u16 = 64;

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

async fn send(sender: &mut Sender<'static, UsbDriver>, bytes: &[u8]) -> Result<(), EndpointError> {
    for chunk in bytes.chunks(PACKET as usize) {
        sender.write_packet(chunk).await?;
    }
    if !bytes.is_empty() && bytes.len() % PACKET as usize == 0 {
        // A full last packet: end the transfer with a zero-length packet.
        sender.write_packet(&[]).await?;
    }
    Ok(())
}

#[embassy_executor::task]
pub async fn link_reader(
    mut receiver: Receiver<'static, UsbDriver>,
    device: &'static SharedDevice,
) -> ! {
    let mut link = DeviceLink::new();
    let mut rx = [0u8; PACKET as usize];
    loop {
        receiver.wait_connection().await;
        defmt::info!("link: host connected");
        link.reset();
        loop {
            let n = match receiver.read_packet(&mut rx).await {
                Ok(n) => n,
                Err(_) => break,
            };
            let mut rest = rx.get(..n).unwrap_or(&[]);
            while !rest.is_empty() {
                let now_us = Instant::now().as_micros();
                let (used, reply) = link.push(rest, |request, counters| {
                    let counters = LinkCounters {
                        tx_frames: counters
                            .tx_frames
                            .wrapping_add(STREAM_FRAMES_SENT.load(Ordering::Relaxed)),
                        ..counters
                    };
                    with_device(device, |d| {
                        d.set_link_counters(counters);
                        d.handle(request, now_us)
                    })
                    .unwrap_or(spidar_protocol::Response::Error(
                        spidar_protocol::DeviceError::Unsupported,
                    ))
                });
                rest = rest.get(used..).unwrap_or(&[]);
                if let Some(reply) = reply {
                    if let Ok(frame) = Frame::from_slice(reply) {
                        REPLIES.send(frame).await;
                    }
                }
            }
        }
        defmt::info!("link: host disconnected");
    }
}

#[embassy_executor::task]
pub async fn link_writer(mut sender: Sender<'static, UsbDriver>) -> ! {
    let mut buf = [0u8; spidar_protocol::MAX_FRAME];
    let mut stream_seq: u16 = 0;
    loop {
        sender.wait_connection().await;
        loop {
            let sent = match select(REPLIES.receive(), STREAM.receive()).await {
                Either::First(reply) => send(&mut sender, &reply).await,
                Either::Second(item) => {
                    let msg = match item {
                        StreamItem::State(s) => DeviceMessage::State(s),
                        StreamItem::Event(e) => DeviceMessage::Event(e),
                    };
                    match encode_device_message(stream_seq, &msg, &mut buf) {
                        Ok(frame) => {
                            stream_seq = stream_seq.wrapping_add(1);
                            STREAM_FRAMES_SENT.fetch_add(1, Ordering::Relaxed);
                            send(&mut sender, frame).await
                        }
                        Err(_) => Ok(()),
                    }
                }
            };
            if sent.is_err() {
                break;
            }
        }
    }
}

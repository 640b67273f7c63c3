//! Requesting a chip's lines of a GPIO card: one request per chip, each line with its
//! direction, bias, polarity, debounce, edge detection, drive and (outputs) the level it
//! is to have from the request on; the descriptor made non-blocking for the bus side's
//! reads and the devices' ioctls. An error names the line and, when another consumer
//! holds it, that consumer.

use crate::card::{GpioCard, Opened, Setup};
use crate::chips::{ChipError, ChipId};
use crate::config::{Bias, Drive, Edges};
use gpiocdev::line::{self, EdgeDetection, Value};
use std::fs::File;
use std::os::fd::AsFd;
use std::time::Duration;

/// Why a card's lines on a chip could not be requested, or read once requested.
#[derive(Debug, thiserror::Error)]
pub enum LinesError {
    /// The chip is not there (again).
    #[error(transparent)]
    Chip(#[from] ChipError),
    /// A line is held by another consumer.
    #[error("{line} is used by {consumer:?}: it cannot be requested ({why})")]
    Busy {
        /// The line.
        line: String,
        /// Who holds it.
        consumer: String,
        /// The kernel's error.
        why: String,
    },
    /// The kernel refused the request or its descriptor (the chip, and why).
    #[error("{chip}: {why}")]
    Refused {
        /// The chip.
        chip: String,
        /// What was refused, and the error.
        why: String,
    },
    /// Requested, the lines could not be read.
    #[error(transparent)]
    Read(#[from] device_interface::DeviceError),
    /// Requested, the descriptor could not be watched.
    #[error(transparent)]
    Watch(#[from] rtt::activity::ActivityError),
}

fn bias(b: Bias) -> Option<line::Bias> {
    match b {
        Bias::AsIs => None,
        Bias::PullUp => Some(line::Bias::PullUp),
        Bias::PullDown => Some(line::Bias::PullDown),
        Bias::Disabled => Some(line::Bias::Disabled),
    }
}

fn edges(e: Edges) -> Option<EdgeDetection> {
    match e {
        Edges::Both => Some(EdgeDetection::BothEdges),
        Edges::Rising => Some(EdgeDetection::RisingEdge),
        Edges::Falling => Some(EdgeDetection::FallingEdge),
        Edges::None => None,
    }
}

/// Requests the lines of the card's chip number `index`, found now as `chip`; outputs at
/// the level the card has for them ([`GpioCard::output_level`]: the initial value until
/// one is written).
pub(crate) fn request(card: &GpioCard, index: usize, chip: ChipId) -> Result<Opened, LinesError> {
    let refused = |why: String| LinesError::Refused {
        chip: chip.name.clone(),
        why,
    };
    let Some(c) = card.chips.get(index) else {
        return Err(refused(format!("the card has no chip {index}")));
    };
    let chip = &chip;
    let mut b = gpiocdev::Request::builder();
    b.on_chip(&chip.path).with_consumer(card.consumer.as_str());
    let inputs_with_edges = c
        .lines
        .iter()
        .filter(|l| matches!(l.setup, Setup::Input { edges, .. } if edges != Edges::None))
        .count() as u32;
    let depth = card
        .event_buffer
        .unwrap_or((16 * inputs_with_edges).clamp(16, crate::config::MAX_EVENT_BUFFER));
    b.with_kernel_event_buffer_size(depth);
    for (bit, l) in c.lines.iter().enumerate() {
        b.with_line(l.id.offset);
        match l.setup {
            Setup::Input {
                bias: bi,
                active_low,
                debounce_us,
                edges: e,
            } => {
                b.as_input()
                    .with_bias(bias(bi))
                    .with_edge_detection(edges(e));
                if active_low {
                    b.as_active_low();
                }
                if debounce_us > 0 {
                    b.with_debounce_period(Duration::from_micros(u64::from(debounce_us)));
                }
            }
            Setup::Output {
                drive,
                bias: bi,
                active_low,
                initial,
            } => {
                let level = card.output_level(index, bit as u32).unwrap_or(initial);
                b.as_output(if level {
                    Value::Active
                } else {
                    Value::Inactive
                })
                .with_bias(bias(bi))
                .with_drive(match drive {
                    Drive::PushPull => line::Drive::PushPull,
                    Drive::OpenDrain => line::Drive::OpenDrain,
                    Drive::OpenSource => line::Drive::OpenSource,
                });
                if active_low {
                    b.as_active_low();
                }
            }
        }
    }
    let request = b.request().map_err(|e| {
        // Name who holds a line, when one is held.
        for l in &c.lines {
            if let Ok(now) = crate::chips::line(
                Some(&chip.path.to_string_lossy()),
                &crate::config::LineRef::Offset(l.id.offset),
            ) && let Some(who) = &now.used_by
            {
                return LinesError::Busy {
                    line: now.to_string(),
                    consumer: who.clone(),
                    why: e.to_string(),
                };
            }
        }
        LinesError::Refused {
            chip: format!("{} ({})", chip.name, chip.label),
            why: format!(
                "requesting lines {:?}: {e}",
                c.lines.iter().map(|l| l.id.offset).collect::<Vec<_>>()
            ),
        }
    })?;
    // Line values address the lines by their index in the request: it must be ours.
    let order: Vec<u32> = c.lines.iter().map(|l| l.id.offset).collect();
    if request.config().lines() != &order {
        return Err(refused(format!(
            "the request has lines {:?}, the card expected {order:?}",
            request.config().lines()
        )));
    }
    let fd = request
        .as_fd()
        .try_clone_to_owned()
        .map_err(|e| refused(e.to_string()))?;
    let flags = nix::fcntl::fcntl(&fd, nix::fcntl::FcntlArg::F_GETFL)
        .map_err(|e| refused(e.to_string()))?;
    let flags = nix::fcntl::OFlag::from_bits_truncate(flags) | nix::fcntl::OFlag::O_NONBLOCK;
    nix::fcntl::fcntl(&fd, nix::fcntl::FcntlArg::F_SETFL(flags))
        .map_err(|e| refused(e.to_string()))?;
    Ok(Opened {
        _request: request,
        file: File::from(fd),
        chip: chip.clone(),
    })
}

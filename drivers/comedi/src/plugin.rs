//! The comedi card as an hwgw driver plug-in (`driver = "comedi"`, section
//! [`ComediConfig`]).
//!
//! Building opens the board only to read its description (subdevices, channels, range
//! tables: the devices' channels and scales come from it) and closes it again: nothing is
//! configured or written until the bus side starts, so `hwgw check` drives nothing. One
//! card per board: a second card on the same device file is refused.

use crate::board::{Board, BoardDesc, Daq};
use crate::bus::ComediBus;
use crate::card::ComediCard;
use crate::config::ComediConfig;
use crate::layout::{Layout, resolve};
use device_interface::CardDevices;
use device_interface::time::Clock;
use driver_api::{
    BuiltCard, BusSide, Card, CardContext, CardError, CardStatus, ReadBack, SettleError,
};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

/// A section built: the card and its board's description.
pub struct Built {
    /// The card (offline until its bus side opens the board).
    pub card: Arc<ComediCard>,
    /// The board as found at build.
    pub desc: BoardDesc,
}

impl Built {
    /// Its bus side, opening real boards.
    pub fn bus(self) -> ComediBus {
        ComediBus::new(self.card, self.desc, Box::new(open))
    }
}

/// Opens a real board.
pub fn open(path: &str) -> Result<Box<dyn Daq>, crate::board::ComediError> {
    Board::open(path).map(|b| Box::new(b) as Box<dyn Daq>)
}

/// The comedi device files present, for errors.
fn present() -> String {
    let mut found: Vec<String> = std::fs::read_dir("/dev")
        .map(|d| {
            d.flatten()
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .filter(|n| n.starts_with("comedi"))
                .map(|n| format!("/dev/{n}"))
                .collect()
        })
        .unwrap_or_default();
    found.sort();
    if found.is_empty() {
        "none (is the comedi module loaded?)".into()
    } else {
        format!(
            "{} (a board is attached to one with comedi_config, or by its driver)",
            found.join(", ")
        )
    }
}

/// The card of a section: the board's description read, the section resolved against it.
pub fn card(config: &ComediConfig, clock: Arc<dyn Clock>) -> Result<Built, CardError> {
    config.check()?;
    let desc = Board::open(&config.device)
        .and_then(|mut b| b.describe())
        .map_err(|e| CardError::at("device", format!("{e}; comedi devices here: {}", present())))?;
    let layout: Layout = resolve(config, &desc)?;
    let name = format!("{} ({})", desc.board, desc.driver);
    let card = ComediCard::new(&config.device, &name, layout, clock)
        .map_err(|e| CardError::at("encoder", e))?;
    Ok(Built {
        card: Arc::new(card),
        desc,
    })
}

/// The boards the deployment's comedi cards use: device file → card.
#[derive(Default)]
struct Claimed(std::collections::HashMap<PathBuf, String>);

struct ComediPlugin {
    card: Arc<ComediCard>,
    period: Duration,
}

/// Builds the card a section describes; its bus side polls the board every `poll_ms`.
pub fn build(config: &ComediConfig, ctx: &mut CardContext<'_>) -> Result<BuiltCard, CardError> {
    let built = card(config, ctx.clock())?;
    let path = Path::new(&config.device);
    let path = std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf());
    let name = ctx.name().to_string();
    let claimed = ctx.shared::<Claimed>();
    if let Some(other) = claimed.0.get(&path) {
        return Err(CardError::at(
            "device",
            format!("{} is card {other:?}'s already", path.display()),
        ));
    }
    claimed.0.insert(path, name);
    let period = Duration::from_millis(u64::from(config.poll_ms));
    let card = built.card.clone();
    let mut bus = built.bus();
    let bus = BusSide::periodic(period, move || bus.step(std::time::Instant::now()));
    Ok(BuiltCard::new(ComediPlugin { card, period }, bus))
}

impl Card for ComediPlugin {
    fn devices(&self) -> CardDevices {
        self.card.devices()
    }

    /// Outputs read back what the board said at open, then what was written.
    fn read_back(&self) -> ReadBack {
        let card = self.card.clone();
        ReadBack::DeviceWhen(Arc::new(move || card.is_online()))
    }

    fn summary(&self) -> String {
        let c = self.card.counters();
        format!(
            "{} {}: {} analog in, {} analog out, {} digital in, {} digital out, {} counters, polled every {} ms",
            self.card.path(),
            c.board,
            device_interface::AnalogIn::channel_count(self.card.as_ref()),
            device_interface::AnalogOut::channel_count(self.card.as_ref()),
            device_interface::DigitalIn::input_count(self.card.as_ref()),
            device_interface::DigitalOut::output_count(self.card.as_ref()),
            self.card.devices().encoders.len(),
            self.period.as_millis()
        )
    }

    /// Outputs are written at once; this stops the board being opened again and says
    /// whether it was online to take them (it is not without its bus side: that opens it).
    fn settle(&self, _deadline: std::time::Instant, _bus_running: bool) -> Result<(), SettleError> {
        self.card.settle()
    }

    fn status(&self) -> CardStatus {
        CardStatus::new(self.card.path(), &self.card.counters())
    }
}

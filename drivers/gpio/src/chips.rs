//! Finding chips and lines: a chip by path, name or label, a line by offset or by the
//! name the kernel gives it; errors list what exists.

use crate::config::LineRef;
use gpiocdev::chip::Chip;
use std::path::{Path, PathBuf};

/// The most chips or lines an error lists before it says "…".
const LISTED: usize = 16;

/// Why a chip or a line was not found; each message says what there is instead.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ChipError {
    /// The path is no GPIO chip, or the chip could not be opened or read.
    #[error("{path}: {why}")]
    Open {
        /// The path given.
        path: String,
        /// What it is instead, or the OS error.
        why: String,
    },
    /// No chip, or several, answer to a name or label: which chips there are.
    #[error("{0}")]
    Chip(String),
    /// No line, or several, answer to an offset or a name on the chips: which there are.
    #[error("{0}")]
    Line(String),
    /// A chip that went away is not back (yet), or came back with other lines.
    #[error("{0}")]
    NotBack(String),
}

/// A chip at `path` that could not be opened or read: `why`.
fn cannot_open(path: &Path, why: impl std::fmt::Display) -> ChipError {
    ChipError::Open {
        path: path.display().to_string(),
        why: why.to_string(),
    }
}

/// A chip found.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ChipId {
    /// Its character device.
    pub path: PathBuf,
    /// Its name (`gpiochip0`).
    pub name: String,
    /// Its label (`gpio-sim.0-node0`).
    pub label: String,
    /// Its number of lines.
    pub lines: u32,
}

/// A line found.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LineId {
    /// Its chip.
    pub chip: ChipId,
    /// Its offset on the chip.
    pub offset: u32,
    /// The kernel's name for it (may be empty).
    pub name: String,
    /// Who holds it now, when it is in use (`consumer`, or `"?"` for an unnamed one).
    pub used_by: Option<String>,
}

impl std::fmt::Display for LineId {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "line {} of {} ({})",
            self.offset, self.chip.name, self.chip.label
        )?;
        if !self.name.is_empty() {
            write!(f, " {:?}", self.name)?;
        }
        Ok(())
    }
}

fn open(path: &Path) -> Result<(Chip, ChipId), ChipError> {
    // gpiocdev's own check needs a file name and a character device: make sure first.
    let canonical = std::fs::canonicalize(path).map_err(|e| cannot_open(path, e))?;
    let node = driver_api::node::Node::of(&canonical).map_err(|e| cannot_open(path, e))?;
    if canonical.file_name().is_none() || !matches!(node, driver_api::node::Node::Char { .. }) {
        let why = format!("not a GPIO character device: it is {node}");
        return Err(cannot_open(path, why));
    }
    let chip = Chip::from_path(&canonical).map_err(|e| match e {
        gpiocdev::Error::GpioChip(..) => cannot_open(
            path,
            format!(
                "not a GPIO character device: it is {node}, which no GPIO chip has (a GPIO \
                 chip is /dev/gpiochipN)"
            ),
        ),
        e => cannot_open(path, e),
    })?;
    let info = chip.info().map_err(|e| cannot_open(path, e))?;
    let id = ChipId {
        path: canonical,
        name: info.name,
        label: info.label,
        lines: info.num_lines,
    };
    Ok((chip, id))
}

/// Every chip of the system, in order (`gpiochip0`, `gpiochip1`, …).
pub fn all() -> Vec<(Chip, ChipId)> {
    gpiocdev::chip::chips()
        .unwrap_or_default()
        .iter()
        .filter_map(|p| open(p).ok())
        .collect()
}

fn listing(chips: &[(Chip, ChipId)]) -> String {
    if chips.is_empty() {
        return "there are no GPIO chips".into();
    }
    let mut names: Vec<String> = chips
        .iter()
        .take(LISTED)
        .map(|(_, c)| format!("{} ({}, {} lines)", c.name, c.label, c.lines))
        .collect();
    if chips.len() > LISTED {
        names.push("…".into());
    }
    format!("the chips are {}", names.join(", "))
}

/// The chip `spec` names: a path (anything with a `/`), else a chip name or label.
pub fn chip(spec: &str) -> Result<(Chip, ChipId), ChipError> {
    if spec.contains('/') {
        return open(Path::new(spec));
    }
    let mut chips = all();
    let found: Vec<usize> = (0..chips.len())
        .filter(|&i| chips[i].1.name == spec || chips[i].1.label == spec)
        .collect();
    match found.len() {
        0 => Err(ChipError::Chip(format!(
            "no GPIO chip named or labelled {spec:?}; {}",
            listing(&chips)
        ))),
        1 => Ok(chips.swap_remove(found[0])),
        _ => Err(ChipError::Chip(format!(
            "{} chips are labelled {spec:?} ({}); give the chip's name or path",
            found.len(),
            found
                .iter()
                .map(|&i| chips[i].1.name.clone())
                .collect::<Vec<_>>()
                .join(", ")
        ))),
    }
}

fn line_on(chip: &Chip, id: &ChipId, offset: u32) -> Result<LineId, ChipError> {
    if offset >= id.lines {
        return Err(ChipError::Line(format!(
            "{} ({}) has lines 0..={}; there is no line {offset}",
            id.name,
            id.label,
            id.lines.saturating_sub(1)
        )));
    }
    let info = chip
        .line_info(offset)
        .map_err(|e| ChipError::Line(format!("line {offset} of {}: {e}", id.name)))?;
    Ok(LineId {
        chip: id.clone(),
        offset,
        name: info.name,
        used_by: info.used.then(|| {
            if info.consumer.is_empty() {
                "?".to_string()
            } else {
                info.consumer
            }
        }),
    })
}

/// Finds `line` on `chip` (a spec as [`chip`] takes), or by name across every chip.
pub fn line(chip_spec: Option<&str>, line: &LineRef) -> Result<LineId, ChipError> {
    match (chip_spec, line) {
        (Some(spec), LineRef::Offset(o)) => {
            let (c, id) = chip(spec)?;
            line_on(&c, &id, *o)
        }
        (None, LineRef::Offset(o)) => Err(ChipError::Line(format!("line {o}: on which chip?"))),
        (Some(spec), LineRef::Name(n)) => {
            let (c, id) = chip(spec)?;
            let named = lines_named(&c, &id, n);
            match named.as_slice() {
                [one] => line_on(&c, &id, *one),
                [] => Err(ChipError::Line(format!(
                    "{} ({}) has no line named {n:?}; {}",
                    id.name,
                    id.label,
                    names_of(&c, &id)
                ))),
                many => Err(ChipError::Line(format!(
                    "{} ({}) has {} lines named {n:?} (offsets {many:?}); give the offset",
                    id.name,
                    id.label,
                    many.len()
                ))),
            }
        }
        (None, LineRef::Name(n)) => {
            let chips = all();
            let mut hits = Vec::new();
            for (c, id) in &chips {
                for o in lines_named(c, id, n) {
                    hits.push((c, id, o));
                }
            }
            match hits.as_slice() {
                [(c, id, o)] => line_on(c, id, *o),
                [] => Err(ChipError::Line(format!(
                    "no GPIO line is named {n:?}; {}",
                    listing(&chips)
                ))),
                many => Err(ChipError::Line(format!(
                    "{} lines are named {n:?} ({}); give `chip`",
                    many.len(),
                    many.iter()
                        .map(|(_, id, o)| format!("{} line {o}", id.name))
                        .collect::<Vec<_>>()
                        .join(", ")
                ))),
            }
        }
    }
}

fn lines_named(chip: &Chip, id: &ChipId, name: &str) -> Vec<u32> {
    (0..id.lines)
        .filter(|&o| chip.line_info(o).is_ok_and(|i| i.name == name))
        .collect()
}

fn names_of(chip: &Chip, id: &ChipId) -> String {
    let named: Vec<String> = (0..id.lines)
        .filter_map(|o| {
            let i = chip.line_info(o).ok()?;
            (!i.name.is_empty()).then(|| format!("{o}={}", i.name))
        })
        .collect();
    if named.is_empty() {
        return "its lines have no names".into();
    }
    let mut shown: Vec<String> = named.iter().take(LISTED).cloned().collect();
    if named.len() > LISTED {
        shown.push("…".into());
    }
    format!("its named lines are {}", shown.join(", "))
}

/// The chip `was` again, after it went away: at its old path if that is a chip with the
/// same label and number of lines, else the one such chip anywhere whose lines at
/// `offsets` nobody holds (a USB adapter plugged back may get another number; an identical
/// one in use elsewhere is not it). Its lines at `named` offsets must still bear those
/// names. An error says why it is not (yet) there.
pub fn again(was: &ChipId, offsets: &[u32], named: &[(u32, &str)]) -> Result<ChipId, ChipError> {
    let same = |id: &ChipId| id.label == was.label && id.lines == was.lines;
    let free = |chip: &Chip, id: &ChipId| {
        offsets
            .iter()
            .all(|&o| line_on(chip, id, o).is_ok_and(|l| l.used_by.is_none()))
    };
    let (chip, id) = match open(&was.path) {
        Ok((c, id)) if same(&id) => (c, id),
        _ => {
            let mut found: Vec<(Chip, ChipId)> = all()
                .into_iter()
                .filter(|(c, id)| same(id) && free(c, id))
                .collect();
            match found.len() {
                0 => {
                    return Err(ChipError::NotBack(format!(
                        "no GPIO chip labelled {:?} with {} lines has lines {offsets:?} free",
                        was.label, was.lines
                    )));
                }
                1 => found.swap_remove(0),
                n => {
                    return Err(ChipError::NotBack(format!(
                        "{n} chips are labelled {:?} with {} lines and have lines {offsets:?} \
                         free; which one is it? (give each adapter a label of its own)",
                        was.label, was.lines
                    )));
                }
            }
        }
    };
    for &(offset, name) in named {
        let now = line_on(&chip, &id, offset)?;
        if now.name != name {
            return Err(ChipError::NotBack(format!(
                "{} ({}) is back, but its line {offset} is named {:?}, not {name:?}",
                id.name, id.label, now.name
            )));
        }
    }
    Ok(id)
}

//! The register map: which points a card has, and which device channel each one is.
//!
//! Points become channels in map order, per interface:
//!
//! | table | point | channel |
//! |---|---|---|
//! | coils | — | DigitalOut bit (DigitalIn with `read_only = true`) |
//! | discrete inputs | — | DigitalIn bit |
//! | input registers | value | AnalogIn channel |
//! | input or holding registers | `bit = n` | DigitalIn bit (bit n of the register) |
//! | holding registers | value | AnalogOut channel (AnalogIn with `read_only = true`) |
//! | input or holding registers | `encoder = { resolution = … }` | an Encoder, turns counted on the counter's wrap |
//!
//! The physical value is `register value * scale + offset`, in `unit`. An analog point's
//! raw value is the register value for integer types. A float register's value is read
//! and written exactly (`read`, `write`, `read_back`; see [`value`](crate::value)); it has
//! no integer, so its *raw* value (`read_raw`, `write_raw`) counts steps over a range of
//! ±2^23 steps (`f32`) or ±2^52 (`f64`). By default that range is the type's own, nearly
//! all of it (±2^127 register units for `f32`, ±2^1000 for `f64`): every finite value the
//! register can hold (scaled) is the channel's range, what `write` accepts, and the steps
//! are coarse. A point given `resolution` (a step in register units, e.g. 0.001) has a fine
//! raw grid instead and a range of ±2^23 or ±2^52 steps of it (±8388.608 for an `f32` at
//! 0.001): `write` refuses beyond it; a value read beyond it is still read exactly, and
//! `read_raw` says it is out of range. NaN and infinities are the channel's
//! status ([`DeviceError::NotANumber`](device_interface::DeviceError::NotANumber)), not a
//! fault of the card.
//!
//! ```
//! use driver_modbus::map::{Map, PointConfig, Role};
//!
//! let points: Vec<PointConfig> = toml::from_str::<toml::Table>(r#"
//!     [[point]]
//!     table = "input_registers"
//!     address = 10
//!     type = "i16"
//!     scale = 0.1
//!     unit = "degC"
//! "#)?["point"].clone().try_into()?;
//! let map = Map::new(&points, 0)?;
//! assert_eq!(map.points()[0].role, Role::AnalogIn);
//! assert_eq!(map.points()[0].scale.to_physical(-215), -21.5);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use crate::codec::Layout;
use crate::plan::{Barrier, PlanError, Read, Span, plan, plan_around};
use crate::point::raw_range;
pub use crate::point::{EncoderPoint, PointConfig, Role, default_float_step};
use device_interface::{Scale, Unit};

/// A validated point.
#[derive(Debug, Clone, PartialEq)]
pub struct Point {
    /// Its configuration.
    pub config: PointConfig,
    /// The interface it serves.
    pub role: Role,
    /// Its channel (or bit) number within that interface.
    pub channel: u32,
    /// What it occupies on the wire.
    pub span: Span,
    /// How its value sits in the registers.
    pub layout: Layout,
    /// Raw to physical (analog points; identity for digital ones).
    pub scale: Scale,
    /// For float points, the register value of one raw count (1 for integer points).
    pub step: f64,
}

/// Why a map was refused; each names the point.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum MapError {
    /// A point whose fields do not go together.
    #[error("point[{point}].{key}: {problem}")]
    Point {
        /// Index of the point.
        point: usize,
        /// The key at fault.
        key: &'static str,
        /// What is wrong.
        problem: String,
    },
    /// The map cannot be read.
    #[error("{0}")]
    Plan(#[from] PlanError),
}

/// A card's register map: points with their channels, and the reads that poll it.
#[derive(Debug, Clone, PartialEq)]
pub struct Map {
    points: Vec<Point>,
    counts: [u32; 5],
    reads: Vec<Read>,
    /// For each read, the indices into `points` it serves.
    read_points: Vec<Vec<usize>>,
    /// Outputs are polled too.
    read_back: bool,
    /// A read refused with IllegalDataAddress is split where the unit has holes.
    learn_holes: bool,
    /// The gap coalesced across.
    max_gap: u16,
    /// The points polled (inputs, and outputs with read_back), in map order.
    polled: Vec<usize>,
}

/// The `max_gap` that coalesces across any gap the protocol's read limits allow.
pub const ANY_GAP: u16 = 2000;

impl Map {
    /// Validates `configs`, numbers the channels and plans the reads with `max_gap`.
    pub fn new(configs: &[PointConfig], max_gap: u16) -> Result<Map, MapError> {
        Self::with_read_back(configs, max_gap, false)
    }

    /// True when the outputs are polled too (their images show the device's values).
    pub fn reads_outputs(&self) -> bool {
        self.read_back
    }

    /// As [`new`](Self::new); with `read_back`, outputs (coils, holding-register outputs)
    /// are polled too, so their images show what the device holds.
    pub fn with_read_back(
        configs: &[PointConfig],
        max_gap: u16,
        read_back: bool,
    ) -> Result<Map, MapError> {
        let mut points = Vec::new();
        let mut counts = [0u32; 5];
        for (i, c) in configs.iter().enumerate() {
            let bad = |key, problem: String| MapError::Point {
                point: i,
                key,
                problem,
            };
            let (role, step) =
                crate::point::check(configs, i).map_err(|(key, problem)| bad(key, problem))?;
            let bit_table = c.table.is_bits();
            let unit = Unit::new(&c.unit).map_err(|e| bad("unit", e.to_string()))?;
            let factor = c.scale * step;
            let scale = Scale::from_factor(raw_range(c.ty), factor, c.offset, unit)
                .map_err(|e| bad("scale", e.to_string()))?;
            let slot = match role {
                Role::AnalogIn => 0,
                Role::AnalogOut => 1,
                Role::DigitalIn => 2,
                Role::DigitalOut => 3,
                Role::Encoder => 4,
            };
            let channel = counts[slot];
            counts[slot] += 1;
            points.push(Point {
                config: c.clone(),
                role,
                channel,
                span: Span {
                    table: c.table,
                    address: c.address,
                    count: if bit_table {
                        1
                    } else {
                        c.ty.registers() as u16
                    },
                },
                layout: Layout {
                    ty: c.ty,
                    words: c.words,
                    bytes: c.bytes,
                },
                scale,
                step,
            });
        }
        // Inputs are polled; outputs are written on change, and polled too with read_back.
        let polled: Vec<usize> = (0..points.len())
            .filter(|&i| {
                matches!(
                    points[i].role,
                    Role::AnalogIn | Role::DigitalIn | Role::Encoder
                ) || (read_back && matches!(points[i].role, Role::AnalogOut | Role::DigitalOut))
            })
            .collect();
        let spans: Vec<Span> = polled.iter().map(|&i| points[i].span).collect();
        // Errors and reads name points of `spans`: map them back to the map's numbering.
        let mut reads = plan(&spans, max_gap).map_err(|e| e.renumber(|k| polled[k]))?;
        let read_points = reads
            .iter()
            .map(|r| r.points.iter().map(|&k| polled[k]).collect())
            .collect();
        for r in &mut reads {
            r.points = r.points.iter().map(|&k| polled[k]).collect();
        }
        Ok(Map {
            points,
            counts,
            reads,
            read_points,
            read_back,
            learn_holes: false,
            max_gap,
            polled,
        })
    }

    /// The same map, splitting reads the unit refuses with IllegalDataAddress (`on`), or
    /// failing the poll on them (the default).
    pub fn learning_holes(mut self, on: bool) -> Map {
        self.learn_holes = on;
        self
    }

    /// True when a refused read is split where the unit has holes.
    pub fn learns_holes(&self) -> bool {
        self.learn_holes
    }

    /// The reads of one poll that never cross `barriers` (the holes a unit was found to
    /// have), as few as the protocol then allows; the map's own reads with none.
    pub fn reads_around(&self, barriers: &[Barrier]) -> Vec<Read> {
        let spans: Vec<Span> = self.polled.iter().map(|&i| self.points[i].span).collect();
        // The same spans planned at build, so this cannot fail; the map's reads if it did.
        match plan_around(&spans, self.max_gap, barriers) {
            Ok(mut reads) => {
                for r in &mut reads {
                    r.points = r.points.iter().map(|&k| self.polled[k]).collect();
                }
                reads
            }
            Err(_) => self.reads.clone(),
        }
    }

    /// The points, in map order.
    pub fn points(&self) -> &[Point] {
        &self.points
    }

    /// Channel counts: [AnalogIn, AnalogOut, DigitalIn, DigitalOut].
    pub fn counts(&self) -> [u32; 4] {
        [
            self.counts[0],
            self.counts[1],
            self.counts[2],
            self.counts[3],
        ]
    }

    /// Number of encoders.
    pub fn encoder_count(&self) -> u32 {
        self.counts[4]
    }

    /// The reads one poll makes (their `points` index [`points`](Self::points)).
    pub fn reads(&self) -> &[Read] {
        &self.reads
    }

    /// The points read `i` serves.
    pub fn read_points(&self, i: usize) -> &[usize] {
        self.read_points.get(i).map_or(&[], Vec::as_slice)
    }

    /// The point serving channel `channel` of `role`.
    pub fn point(&self, role: Role, channel: u32) -> Option<&Point> {
        self.points
            .iter()
            .find(|p| p.role == role && p.channel == channel)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn points(text: &str) -> Vec<PointConfig> {
        let t: toml::Table = toml::from_str(text).unwrap();
        t["point"].clone().try_into().unwrap()
    }

    #[test]
    fn tables_become_channels_in_map_order() {
        let map = Map::new(
            &points(
                r#"
                [[point]]
                table = "holding_registers"
                address = 0
                [[point]]
                table = "input_registers"
                address = 0
                type = "f32"
                [[point]]
                table = "holding_registers"
                address = 5
                read_only = true
                [[point]]
                table = "coils"
                address = 3
                [[point]]
                table = "input_registers"
                address = 9
                bit = 4
                [[point]]
                table = "discrete_inputs"
                address = 1
                [[point]]
                table = "holding_registers"
                address = 1
                type = "i32"
                "#,
            ),
            0,
        )
        .unwrap();
        let roles: Vec<(Role, u32)> = map.points().iter().map(|p| (p.role, p.channel)).collect();
        assert_eq!(
            roles,
            vec![
                (Role::AnalogOut, 0),
                (Role::AnalogIn, 0),
                (Role::AnalogIn, 1),
                (Role::DigitalOut, 0),
                (Role::DigitalIn, 0),
                (Role::DigitalIn, 1),
                (Role::AnalogOut, 1),
            ]
        );
        assert_eq!(map.counts(), [2, 2, 2, 1]);
        // Only inputs are polled: discrete 1; input registers 0..=1 and 9 (apart); holding 5.
        let reads: Vec<String> = map.reads().iter().map(|r| r.to_string()).collect();
        assert_eq!(
            reads,
            vec![
                "FC2 read discrete inputs 1..=1 (1) for points [5]",
                "FC4 read input registers 0..=1 (2) for points [1]",
                "FC4 read input registers 9..=9 (1) for points [4]",
                "FC3 read holding registers 5..=5 (1) for points [2]",
            ]
        );
        assert_eq!(map.read_points(1), &[1]);
    }

    #[test]
    fn float_raw_values_count_resolution_steps() {
        let map = Map::new(&points("[[point]]\ntable = \"input_registers\"\naddress = 0\ntype = \"f32\"\nscale = 2.0\noffset = 1.0\n[[point]]\ntable = \"input_registers\"\naddress = 2\ntype = \"f32\"\nresolution = 0.5\n"), 0).unwrap();
        let s = map.points()[0].scale;
        let step = 2f64.powi(104);
        assert_eq!(
            s.range().highest,
            2f64.powi(127) * 2.0 + 1.0,
            "the type's range, scaled: register 2^127 -> 2^127 * 2 + 1"
        );
        assert_eq!(s.to_physical(3), 3.0 * step * 2.0 + 1.0);
        assert_eq!(s.resolution(), step * 2.0);
        let fine = map.points()[1].scale;
        assert_eq!(fine.range().highest, 4194304.0, "2^23 steps of 0.5");
        assert_eq!(fine.to_physical(3), 1.5);
    }

    #[test]
    fn bad_points_name_their_key() {
        let cases = [
            (
                "[[point]]\ntable = \"coils\"\naddress = 0\nencoder = { resolution = 100 }\n",
                "point[0].encoder: an encoder is an integer counter register: no bit table, bit field or float",
            ),
            (
                "[[point]]\ntable = \"input_registers\"\naddress = 0\nencoder = { resolution = 0 }\n",
                "point[0].encoder: resolution 0: expected counts per turn, not 0",
            ),
            (
                "[[point]]\ntable = \"input_registers\"\naddress = 0\nresolution = 0.1\n",
                "point[0].resolution: only float points have a resolution; u16 counts whole units",
            ),
            (
                "[[point]]\ntable = \"input_registers\"\naddress = 0\ntype = \"f64\"\nresolution = -1.0\n",
                "point[0].resolution: -1: expected a step above 0",
            ),
            (
                "[[point]]\ntable = \"coils\"\naddress = 0\ntype = \"u32\"\n",
                "point[0].table: coils hold single bits: no type, bit, scale or offset",
            ),
            (
                "[[point]]\ntable = \"input_registers\"\naddress = 0\nbit = 16\n",
                "point[0].bit: 16: a register has bits 0..=15",
            ),
            (
                "[[point]]\ntable = \"input_registers\"\naddress = 0\ntype = \"u32\"\nbit = 1\n",
                "point[0].bit: a bit field needs a 16-bit type, not u32",
            ),
            (
                "[[point]]\ntable = \"input_registers\"\naddress = 0\nread_only = true\n",
                "point[0].read_only: input registers are read-only already; read_only makes a coil or a holding register an input",
            ),
            (
                "[[point]]\ntable = \"coils\"\naddress = 3\n[[point]]\ntable = \"coils\"\naddress = 3\nread_only = true\n",
                "point[1].address: coils 3: point[0] is there already (coils 3)",
            ),
            (
                "[[point]]\ntable = \"holding_registers\"\naddress = 10\ntype = \"u32\"\n[[point]]\ntable = \"holding_registers\"\naddress = 11\n",
                "point[1].address: holding registers 11: point[0] is there already (holding registers 10)",
            ),
            (
                "[[point]]\ntable = \"input_registers\"\naddress = 4\nbit = 3\n[[point]]\ntable = \"input_registers\"\naddress = 4\nbit = 3\n",
                "point[1].address: input registers 4: point[0] is there already (input registers 4, bit 3)",
            ),
            (
                "[[point]]\ntable = \"holding_registers\"\naddress = 4\n[[point]]\ntable = \"holding_registers\"\naddress = 4\nbit = 0\n",
                "point[1].address: holding registers 4: point[0] is there already (holding registers 4)",
            ),
            (
                "[[point]]\ntable = \"input_registers\"\naddress = 0\nscale = 0.0\n",
                "point[0].scale: factor 0 and offset 0 are invalid: needs a finite non-zero factor and a finite offset",
            ),
            (
                "[[point]]\ntable = \"input_registers\"\naddress = 3\n[[point]]\ntable = \"input_registers\"\naddress = 65535\ntype = \"f32\"\n",
                "point[1].address: 65535: a f32 point of 2 registers runs past address 65535",
            ),
        ];
        for (text, want) in cases {
            assert_eq!(Map::new(&points(text), 0).unwrap_err().to_string(), want);
        }
    }
}

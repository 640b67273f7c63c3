//! A CANopen card's section resolved against its nodes' EDS files: the SDO writes that
//! configure each node and the values read back to check them, the PDOs hwgw receives and
//! sends, and the channels their mapped objects become. Every error names the key it is
//! about (`node[0].tpdo[1].objects[2]`) and what is wrong.

use crate::eds::{ObjectDictionary, data_type};
use crate::pdo::{Direction, Mapped, Pdo, Write, type_bits};
use crate::section::{AtStop, CanopenConfig, Kind, NodeConfig, ObjectConfig, PdoConfig};
use can_socket::signal::{ByteOrder, Signal, ValueKind};
use std::path::Path;
use std::time::Duration;

/// Why a section does not resolve: the key, and what is wrong there.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{key}: {message}")]
pub struct MapError {
    /// The key, e.g. `node[0].tpdo[1].objects[2]`.
    pub key: String,
    /// What is wrong.
    pub message: String,
}

fn at(key: impl Into<String>, message: impl std::fmt::Display) -> MapError {
    MapError {
        key: key.into(),
        message: message.to_string(),
    }
}

/// One managed node.
#[derive(Debug, Clone)]
pub struct NodeMap {
    /// Node id.
    pub id: u8,
    /// Its channels' name prefix.
    pub name: String,
    /// The heartbeat period asked of it.
    pub heartbeat: Option<Duration>,
    /// How long without a heartbeat before it is offline.
    pub heartbeat_timeout: Option<Duration>,
    /// The SDO writes that configure it, in order.
    pub setup: Vec<Write>,
    /// What is read back after them: each object's last written value.
    pub verify: Vec<Write>,
    /// The objects its RPDOs carry: read once configured, so that hwgw's outputs start
    /// as the node has them (nothing is written before somebody asks).
    pub outputs: Vec<(u16, u8)>,
    /// Object names for messages (`0x1A00:1` → "TPDO1 mapping entry 1").
    pub od: ObjectDictionary,
}

/// One PDO on the bus.
#[derive(Debug, Clone, PartialEq)]
pub struct PdoMap {
    /// Index into [`CanopenMap::nodes`].
    pub node: usize,
    /// Its COB-ID.
    pub cob_id: u16,
    /// Synchronous (sent after SYNC, for an RPDO).
    pub sync: bool,
    /// Its length, bytes.
    pub len: usize,
    /// e.g. `n5 TPDO1`.
    pub name: String,
}

/// One channel: an object of a PDO (or bit `bit` of a digital object).
#[derive(Debug, Clone)]
pub struct Channel {
    /// Index into the card's TPDOs (inputs) or RPDOs (outputs).
    pub pdo: usize,
    /// Where the object sits in the PDO, and its scale.
    pub signal: Signal,
    /// For a digital channel: the bit of the object.
    pub bit: u32,
    /// Port name.
    pub name: String,
    /// The mapped object, for docs.
    pub object: (u16, u8),
}

/// The resolved section.
#[derive(Debug, Clone)]
pub struct CanopenMap {
    /// The interface.
    pub interface: String,
    /// SYNC period.
    pub sync: Option<Duration>,
    /// SDO response timeout.
    pub sdo_timeout: Duration,
    /// NMT at stop.
    pub at_stop: AtStop,
    /// The nodes.
    pub nodes: Vec<NodeMap>,
    /// The PDOs hwgw receives (the nodes' TPDOs).
    pub tpdos: Vec<PdoMap>,
    /// The PDOs hwgw sends (the nodes' RPDOs).
    pub rpdos: Vec<PdoMap>,
    /// Analog inputs.
    pub analog_in: Vec<Channel>,
    /// Digital inputs.
    pub digital_in: Vec<Channel>,
    /// Analog outputs.
    pub analog_out: Vec<Channel>,
    /// Digital outputs.
    pub digital_out: Vec<Channel>,
    /// The drives' controlwords and target velocities (no channels: the drives own them).
    pub drive_out: Vec<Channel>,
    /// The CiA 402 drives.
    pub drives: Vec<DriveMap>,
}

/// A node's CiA 402 drive, resolved.
#[derive(Debug, Clone)]
pub struct DriveMap {
    /// Index into [`CanopenMap::nodes`].
    pub node: usize,
    /// Its name under the card.
    pub name: String,
    /// Velocity units per count.
    pub factor: f64,
    /// The velocity unit.
    pub unit: String,
    /// Its controlword in [`CanopenMap::drive_out`].
    pub controlword: usize,
    /// Its target velocity in [`CanopenMap::drive_out`].
    pub velocity: usize,
    /// Its statusword in [`CanopenMap::analog_in`].
    pub statusword: usize,
}

impl CanopenMap {
    /// Resolves `config`, EDS paths relative to `base`.
    pub fn new(config: &CanopenConfig, base: &Path) -> Result<CanopenMap, MapError> {
        if config.sync_ms == Some(0) {
            return Err(at("sync_ms", "a SYNC period is at least 1 ms"));
        }
        if config.sdo_timeout_ms == 0 {
            return Err(at("sdo_timeout_ms", "at least 1 ms"));
        }
        let mut map = CanopenMap {
            interface: config.interface.clone(),
            sync: config.sync_ms.map(|ms| Duration::from_millis(ms.into())),
            sdo_timeout: Duration::from_millis(config.sdo_timeout_ms.into()),
            at_stop: config.at_stop,
            nodes: Vec::new(),
            tpdos: Vec::new(),
            rpdos: Vec::new(),
            analog_in: Vec::new(),
            digital_in: Vec::new(),
            analog_out: Vec::new(),
            digital_out: Vec::new(),
            drive_out: Vec::new(),
            drives: Vec::new(),
        };
        for (n, node) in config.node.iter().enumerate() {
            let key = format!("node[{n}]");
            if let Some(other) = config.node[..n].iter().position(|o| o.id == node.id) {
                return Err(at(
                    format!("{key}.id"),
                    format!("node {} is node[{other}] already", node.id),
                ));
            }
            map.add_node(node, &key, base)?;
        }
        if map.sync.is_none()
            && let Some(p) = map.rpdos.iter().find(|p| p.sync)
        {
            return Err(at(
                "sync_ms",
                format!(
                    "{} is synchronous: hwgw sends it after its SYNC, so give sync_ms",
                    p.name
                ),
            ));
        }
        // A PDO on a managed node's service id would take its frames (or send to it).
        for p in map.tpdos.iter().chain(&map.rpdos) {
            let clash = map.nodes.iter().find_map(|n| {
                let id = u16::from(n.id);
                [
                    (0x80 + id, "emergency"),
                    (0x580 + id, "SDO response"),
                    (0x600 + id, "SDO request"),
                    (0x700 + id, "heartbeat"),
                ]
                .into_iter()
                .find(|(c, _)| *c == p.cob_id)
                .map(|(_, what)| format!("node {}'s {what} id", n.id))
            });
            let clash = clash.or_else(|| (p.cob_id == 0x80).then(|| "the SYNC id".to_string()));
            if let Some(what) = clash {
                return Err(at(
                    "node",
                    format!("{}'s COB-ID {:#x} is {what}", p.name, p.cob_id),
                ));
            }
        }
        let mut names: Vec<&str> = [
            &map.analog_in,
            &map.digital_in,
            &map.analog_out,
            &map.digital_out,
        ]
        .iter()
        .flat_map(|c| c.iter().map(|c| c.name.as_str()))
        .collect();
        names.sort();
        if let Some(w) = names.windows(2).find(|w| w[0] == w[1]) {
            return Err(at("node", format!("two channels are named {:?}", w[0])));
        }
        Ok(map)
    }

    fn add_node(&mut self, node: &NodeConfig, key: &str, base: &Path) -> Result<(), MapError> {
        if !(1..=127).contains(&node.id) {
            return Err(at(
                format!("{key}.id"),
                format!("node id {}: expected 1 to 127", node.id),
            ));
        }
        let path = base.join(&node.eds);
        let text = std::fs::read(&path)
            .map_err(|e| at(format!("{key}.eds"), format!("{}: {e}", path.display())))?;
        // EDS files are ASCII by the standard; vendors' tools write Windows-1252.
        let text: String = text.iter().map(|&b| char::from(b)).collect();
        let od = crate::eds::parse(&text, Some(node.id))
            .map_err(|e| at(format!("{key}.eds"), format!("{}: {e}", path.display())))?;
        let name = node.name.clone().unwrap_or_else(|| format!("n{}", node.id));
        let mut setup = Vec::new();
        if let Some(ms) = node.heartbeat_ms {
            if od.variable(0x1017, 0).is_none() {
                return Err(at(
                    format!("{key}.heartbeat_ms"),
                    "the node's EDS has no 0x1017 (producer heartbeat time)",
                ));
            }
            setup.push(Write {
                index: 0x1017,
                sub: 0,
                data: ms.to_le_bytes().to_vec(),
            });
        }
        if node.drive.is_some() {
            // Profile velocity mode.
            setup.push(
                crate::setting::write(&od, "0x6060:0", crate::section::toml_value::Number::Int(3))
                    .map_err(|m| at(format!("{key}.drive"), m))?,
            );
        }
        for (s, setting) in node.sdo.iter().enumerate() {
            let k = format!("{key}.sdo[{s}]");
            setup.push(
                crate::setting::write(&od, &setting.object, setting.value).map_err(|m| at(k, m))?,
            );
        }
        let node_index = self.nodes.len();
        for (direction, list, label) in [
            (Direction::Tpdo, &node.tpdo, "tpdo"),
            (Direction::Rpdo, &node.rpdo, "rpdo"),
        ] {
            for (p, pdo) in list.iter().enumerate() {
                let k = format!("{key}.{label}[{p}]");
                let drive = node.drive.is_some();
                self.add_pdo(
                    (node_index, drive),
                    node.id,
                    &name,
                    &od,
                    direction,
                    pdo,
                    &k,
                    &mut setup,
                )?;
            }
        }
        if let Some(d) = &node.drive {
            self.add_drive(node_index, node.id, d, &format!("{key}.drive"))?;
        }
        // Each readable object's final value, read back once configured (a PDO's COB-ID
        // with its valid bit, not the invalid one written first).
        let mut verify: Vec<Write> = Vec::new();
        let readable = |w: &&Write| {
            od.variable(w.index, w.sub)
                .is_some_and(|v| v.access != crate::eds::Access::Wo)
        };
        for w in setup.iter().filter(readable) {
            verify.retain(|v| (v.index, v.sub) != (w.index, w.sub));
            verify.push(w.clone());
        }
        self.nodes.push(NodeMap {
            id: node.id,
            name,
            heartbeat: node
                .heartbeat_ms
                .filter(|&ms| ms > 0)
                .map(|ms| Duration::from_millis(ms.into())),
            heartbeat_timeout: match (node.heartbeat_timeout_ms, node.heartbeat_ms) {
                (Some(t), _) => Some(Duration::from_millis(t.into())),
                (None, Some(ms)) if ms > 0 => Some(Duration::from_millis(3 * u64::from(ms))),
                _ => None,
            },
            setup,
            verify,
            // A write-only object cannot be read: it starts at 0 in hwgw's image.
            outputs: node
                .rpdo
                .iter()
                .flat_map(|p| &p.objects)
                .filter_map(|o| crate::section::parse_object(&o.object))
                .filter(|&(i, s)| {
                    od.variable(i, s)
                        .is_some_and(|v| v.access != crate::eds::Access::Wo)
                })
                .collect(),
            od,
        });
        Ok(())
    }

    #[allow(
        clippy::too_many_arguments,
        reason = "one PDO of one node: its place and where its writes and channels go"
    )]
    fn add_pdo(
        &mut self,
        (node, drive): (usize, bool),
        id: u8,
        name: &str,
        od: &ObjectDictionary,
        direction: Direction,
        pdo: &PdoConfig,
        key: &str,
        setup: &mut Vec<Write>,
    ) -> Result<(), MapError> {
        let label = if direction == Direction::Tpdo {
            "TPDO"
        } else {
            "RPDO"
        };
        let cob_id = match (pdo.cob_id, pdo.number) {
            (Some(c), _) => c,
            (None, n @ 1..=4) => {
                let base = if direction == Direction::Tpdo {
                    0x180
                } else {
                    0x200
                };
                base + 0x100 * (n - 1) + u16::from(id)
            }
            (None, n) => {
                return Err(at(
                    format!("{key}.cob_id"),
                    format!("{label}{n} has no predefined COB-ID: give one"),
                ));
            }
        };
        let list = if direction == Direction::Tpdo {
            &self.tpdos
        } else {
            &self.rpdos
        };
        if let Some(other) = list
            .iter()
            .chain(if direction == Direction::Tpdo {
                &self.rpdos
            } else {
                &self.tpdos
            })
            .find(|p| p.cob_id == cob_id)
        {
            return Err(at(
                format!("{key}.cob_id"),
                format!("COB-ID {cob_id:#x} is {}'s already", other.name),
            ));
        }
        let mut mapped = Vec::new();
        let mut channels = Vec::new();
        let mut offset = 0u32;
        for (o, obj) in pdo.objects.iter().enumerate() {
            let k = format!("{key}.objects[{o}]");
            let (index, sub) = crate::section::parse_object(&obj.object).ok_or_else(|| {
                at(
                    format!("{k}.object"),
                    format!("{:?}: expected 0xINDEX:SUB", obj.object),
                )
            })?;
            let v = od.variable(index, sub).ok_or_else(|| {
                at(
                    format!("{k}.object"),
                    format!("{index:#06x} sub {sub} is not in the node's dictionary"),
                )
            })?;
            let bits = type_bits(v.data_type).ok_or_else(|| {
                at(
                    format!("{k}.object"),
                    format!(
                        "{index:#06x} sub {sub} ({}) has no fixed size to map",
                        v.name
                    ),
                )
            })?;
            mapped.push(Mapped { index, sub, bits });
            channels.push((k, obj, index, sub, v.data_type, offset, bits));
            offset += u32::from(bits);
        }
        let resolved = Pdo {
            direction,
            number: pdo.number,
            cob_id,
            transmission: pdo.transmission.number(),
            event_timer_ms: pdo.event_timer_ms,
            inhibit_100us: pdo.inhibit_100us,
            mapped,
        };
        setup.extend(resolved.writes(od).map_err(|e| at(key, e))?);
        let pdo_index = list.len();
        let entry = PdoMap {
            node,
            cob_id,
            sync: pdo.transmission.is_sync(),
            len: offset.div_ceil(8) as usize,
            name: format!("{name} {label}{}", pdo.number),
        };
        if direction == Direction::Tpdo {
            self.tpdos.push(entry);
        } else {
            self.rpdos.push(entry);
        }
        for (k, obj, index, sub, data_type, offset, bits) in channels {
            let owned = drive
                && direction == Direction::Rpdo
                && matches!((index, sub), (0x6040, 0) | (0x60FF, 0));
            self.add_channel(
                (direction, owned),
                pdo_index,
                name,
                &k,
                obj,
                (index, sub, data_type),
                offset,
                bits,
            )?;
        }
        Ok(())
    }

    #[allow(
        clippy::too_many_arguments,
        reason = "one mapped object: where it sits, what it is and what the section says"
    )]
    fn add_channel(
        &mut self,
        (direction, owned): (Direction, bool),
        pdo: usize,
        node_name: &str,
        key: &str,
        obj: &ObjectConfig,
        (index, sub, data_type): (u16, u8, u16),
        offset: u32,
        bits: u8,
    ) -> Result<(), MapError> {
        let digital_401 = matches!(index, 0x6000..=0x6020 | 0x6200..=0x6220);
        let kind = obj
            .kind
            .unwrap_or(if data_type == data_type::BOOLEAN || digital_401 {
                Kind::Digital
            } else {
                Kind::Analog
            });
        let name = obj
            .name
            .clone()
            .unwrap_or_else(|| format!("{node_name}_{index:04x}_{sub}"));
        if !driver_api::is_port_name(&name) {
            return Err(at(
                format!("{key}.name"),
                format!("{name:?}: a port name has no dots or spaces"),
            ));
        }
        let signed = data_type::signed_bits(data_type).is_some();
        let is_float = matches!(data_type, data_type::REAL32 | data_type::REAL64);
        if kind == Kind::Digital && is_float {
            return Err(at(
                format!("{key}.type"),
                "a float object cannot be digital",
            ));
        }
        if kind == Kind::Digital && (obj.factor.is_some() || obj.offset.is_some()) {
            return Err(at(
                format!("{key}.factor"),
                "a digital object has no factor or offset",
            ));
        }
        let signal = Signal::new(
            offset,
            u32::from(bits),
            ByteOrder::Intel,
            signed && kind == Kind::Analog,
            obj.factor.unwrap_or(1.0),
            obj.offset.unwrap_or(0.0),
            obj.unit.as_deref().unwrap_or(""),
        )
        .and_then(|s| match data_type {
            data_type::REAL32 => s.with_kind(ValueKind::Float32),
            data_type::REAL64 => s.with_kind(ValueKind::Float64),
            _ => Ok(s),
        })
        .map_err(|e| at(key, e))?;
        let list = match (direction, kind) {
            // A drive's controlword and target velocity: its own, not a channel.
            _ if owned => &mut self.drive_out,
            (Direction::Tpdo, Kind::Analog) => &mut self.analog_in,
            (Direction::Tpdo, Kind::Digital) => &mut self.digital_in,
            (Direction::Rpdo, Kind::Analog) => &mut self.analog_out,
            (Direction::Rpdo, Kind::Digital) => &mut self.digital_out,
        };
        let width = if kind == Kind::Digital {
            u32::from(bits)
        } else {
            1
        };
        for bit in 0..width {
            list.push(Channel {
                pdo,
                signal: signal.clone(),
                bit,
                name: if width == 1 {
                    name.clone()
                } else {
                    format!("{name}_{bit}")
                },
                object: (index, sub),
            });
        }
        Ok(())
    }
}

impl CanopenMap {
    /// Node `node`'s drive: its RPDOs must carry the controlword and the target velocity,
    /// a TPDO its statusword.
    fn add_drive(
        &mut self,
        node: usize,
        id: u8,
        d: &crate::section::DriveConfig,
        key: &str,
    ) -> Result<(), MapError> {
        let of_node = |c: &Channel, pdos: &[PdoMap]| pdos[c.pdo].node == node;
        let out = |object: (u16, u8)| {
            self.drive_out
                .iter()
                .position(|c| c.object == object && of_node(c, &self.rpdos))
        };
        let (Some(controlword), Some(velocity)) = (out((0x6040, 0)), out((0x60FF, 0))) else {
            return Err(at(
                key,
                "a drive's RPDOs carry its controlword (0x6040:0) and target velocity (0x60FF:0)",
            ));
        };
        let Some(statusword) = self
            .analog_in
            .iter()
            .position(|c| c.object == (0x6041, 0) && of_node(c, &self.tpdos))
        else {
            return Err(at(
                key,
                "a drive's TPDO carries its statusword (0x6041:0), mapped as analog",
            ));
        };
        let factor = d.velocity_factor.unwrap_or(1.0);
        if !factor.is_finite() || factor == 0.0 {
            return Err(at(
                format!("{key}.velocity_factor"),
                format!("{factor}: a finite number other than 0"),
            ));
        }
        let name = d.name.clone().unwrap_or_else(|| format!("drive{id}"));
        if !driver_api::is_port_name(&name) || self.drives.iter().any(|o| o.name == name) {
            return Err(at(
                format!("{key}.name"),
                format!("{name:?}: a drive needs a name of its own without dots or spaces"),
            ));
        }
        self.drives.push(DriveMap {
            node,
            name,
            factor,
            unit: d.unit.clone().unwrap_or_else(|| "counts/s".into()),
            controlword,
            velocity,
            statusword,
        });
        Ok(())
    }
}

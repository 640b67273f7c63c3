//! CANopen for hwgw (CiA 301), `driver = "canopen"`: a manager for the nodes a deployment
//! lists, on the SocketCAN layer it shares with the DBC cards (`can-socket`).
//!
//! - [`eds`]: a node's object dictionary read from its EDS (CiA 306, the INI file a
//!   vendor ships): objects, sub-indices, data types, access, defaults with `$NODEID`,
//!   limits, PDO mapping — checked against Python `canopen`'s reading of the same files;
//! - [`sdo`]: the SDO client, expedited and segmented upload and download, as a state
//!   machine without I/O; aborts named by CiA 301's table;
//! - [`pdo`]: a PDO's mapping and communication parameters checked against the node's
//!   dictionary, and the SDO writes that configure it in CiA 301's order;
//! - [`section`] and [`map`]: `[card.canopen]` as written, and resolved against the EDS
//!   files into each node's configuration, the PDOs and the channels;
//! - [`node`]: one node's life without I/O — NMT reset, boot-up, configuration by SDO and
//!   read-back, start, heartbeat watched, emergencies counted;
//! - [`card`]: the PDO images as AnalogIn/Out and DigitalIn/Out; [`bus`]: the socket,
//!   SYNC producer and timers; [`component`]: the bus as an rtt component; [`plugin`]:
//!   the driver.
//!
//! ```
//! let od = driver_canopen::eds::parse(
//!     "[1017]\nParameterName=Producer heartbeat time\nDataType=0x0006\nAccessType=rw\nDefaultValue=500\n",
//!     Some(5),
//! )?;
//! let hb = od.variable(0x1017, 0).expect("1017");
//! assert_eq!(hb.default, Some(driver_canopen::eds::Value::Int(500)));
//! # Ok::<(), driver_canopen::eds::EdsError>(())
//! ```

pub mod bus;
pub mod card;
pub mod cia402;
pub mod component;
pub mod drive;
pub mod eds;
pub mod map;
pub mod node;
pub mod pdo;
pub mod plugin;
pub mod sdo;
pub mod section;
pub mod setting;

//! CANopen for hwgw (CiA 301), growing with its issue. What is here:
//!
//! - [`eds`]: a node's object dictionary read from its EDS (CiA 306, the INI file a
//!   vendor ships): objects, sub-indices, data types, access, defaults with `$NODEID`,
//!   limits, PDO mapping — checked against Python `canopen`'s reading of the same files;
//! - [`sdo`]: the SDO client, expedited and segmented upload and download, as a state
//!   machine without I/O; aborts named by CiA 301's table;
//! - [`pdo`]: a PDO's mapping and communication parameters checked against the node's
//!   dictionary, and the SDO writes that configure it in CiA 301's order.
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

pub mod eds;
pub mod pdo;
pub mod sdo;

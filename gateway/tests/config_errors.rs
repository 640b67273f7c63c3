//! Broken deployments and the exact error each must produce: file, line, column, key path
//! and what was expected. The same code path as `hwgw check` and `hwgw run`.

use hwgw::deploy::Gateway;

const CARD: &str = r#"[[card]]
name = "sim0"
driver = "sim"
[card.sim]
digital_outputs = 8
[[card.sim.analog_in]]
range = { lowest = -10.0, highest = 10.0 }
waveform = { kind = "constant", value = 1.0 }
[[card.sim.analog_out]]
range = { lowest = 0.0, highest = 10.0 }
"#;

const CAN: &str = "[[card]]\nname = \"can\"\ndriver = \"socketcan\"\n[card.socketcan]\n";
const CANOPEN: &str = "[[card]]\nname = \"io\"\ndriver = \"canopen\"\n[card.canopen]\ninterface = \"can7\"\n[[card.canopen.node]]\nid = 5\neds = \"../drivers/canopen/tests/eds/io401.eds\"\n";

/// Every error `text` produces, one per line, or "ok".
fn errors(text: &str) -> String {
    errors_in(text, "t.toml")
}

/// As [`errors`], for `text` read from `file` (files it names are relative to it).
fn errors_in(text: &str, file: &str) -> String {
    match Gateway::from_text(text, file, &hwgw::types::Types::builtin()) {
        Ok(_) => "ok".to_string(),
        Err(e) => e,
    }
}

fn with_card(rest: &str) -> String {
    format!("{CARD}{rest}")
}

#[test]
fn every_broken_config_gets_its_exact_error() {
    let cpus = std::thread::available_parallelism().map_or(1, usize::from);
    let cases: Vec<(&str, String, &str)> = vec![
        ("unknown top-level key", "thread_scop = true\n".into(),
         "t.toml:1:1: thread_scop: unknown key \"thread_scop\"; a deployment has thread_scope, thread_scope_vcd, thread_scope_vcd_keep, cpu_dma_latency_us, control_socket, control_clients, control_idle_s, card, alias, logical, component, connection, zenoh, and the servers of this build: modbus_server, server.foxglove, server.metrics, server.mqtt, server.opcua, server.web"),
        ("an unknown top-level table", format!("{CARD}[modbus_servr]\nlisten = \"127.0.0.1:0\"\n"),
         "t.toml:11:2: modbus_servr: unknown key \"modbus_servr\"; a deployment has thread_scope, thread_scope_vcd, thread_scope_vcd_keep, cpu_dma_latency_us, control_socket, control_clients, control_idle_s, card, alias, logical, component, connection, zenoh, and the servers of this build: modbus_server, server.foxglove, server.metrics, server.mqtt, server.opcua, server.web"),
        ("a server under [server] this build lacks", format!("{CARD}[server.metrcs]\n"),
         "t.toml:11:9: server.metrcs: unknown key \"server.metrcs\"; a deployment has thread_scope, thread_scope_vcd, thread_scope_vcd_keep, cpu_dma_latency_us, control_socket, control_clients, control_idle_s, card, alias, logical, component, connection, zenoh, and the servers of this build: modbus_server, server.foxglove, server.metrics, server.mqtt, server.opcua, server.web"),
        ("[server] holding no table", format!("server = 5\n{CARD}"),
         "t.toml:1:10: server: [server] holds a table for each server: [server.NAME]"),
        ("web: writes without a token", format!("{CARD}[server.web]\nallow_writes = true\n"),
         "t.toml:11:1: server.web.token: allow_writes needs a token"),
        ("web: a short token", format!("{CARD}[server.web]\ntoken = \"short\"\n"),
         "t.toml:12:9: server.web.token: at least 16 characters"),
        ("mqtt: a broker without its port", format!("{CARD}[server.mqtt]\nbroker = \"localhost\"\n[server.mqtt.json]\n"),
         "t.toml:12:10: server.mqtt.broker: \"localhost\": no port (host:port, e.g. 127.0.0.1:1883)"),
        ("mqtt: nothing to publish", format!("{CARD}[server.mqtt]\nbroker = \"b:1883\"\n"),
         "t.toml:11:1: server.mqtt: nothing to publish: give [server.mqtt.sparkplug], [server.mqtt.json] or both"),
        ("mqtt: a Sparkplug id that is no topic level", format!("{CARD}[server.mqtt]\nbroker = \"b:1883\"\n[server.mqtt.sparkplug]\ngroup = \"g\"\nnode = \"a/b\"\n"),
         "t.toml:15:8: server.mqtt.sparkplug.node: \"a/b\": '/' is not allowed in a topic level"),
        ("mqtt: a deadband of no channel", format!("{CARD}[server.mqtt]\nbroker = \"b:1883\"\ndeadbands = {{ \"sim0.ai.ch9\" = 0.5 }}\n[server.mqtt.json]\n"),
         "t.toml:13:13: server.mqtt.deadbands.sim0.ai.ch9: \"sim0.ai.ch9\" is no published channel (component.port, e.g. sim0.ai.ch0)"),
        ("mqtt: a device that is not there", format!("{CARD}[server.mqtt]\nbroker = \"b:1883\"\ndevices = [\"sim9\"]\n[server.mqtt.json]\n"),
         "t.toml:13:12: server.mqtt.devices[0]: no device \"sim9\"; the devices: sim0"),
        ("opcua: None on a network address", format!("{CARD}[server.opcua]\nlisten = \"0.0.0.0:4840\"\npki_dir = \"pki\"\n"),
         "t.toml:11:1: server.opcua.security: \"none\" on 0.0.0.0:4840, which is not loopback, lets anyone on the network in unsigned: leave it out, or set allow_none_remote = true"),
        ("opcua: a listen address without a port", format!("{CARD}[server.opcua]\nlisten = \"127.0.0.1\"\npki_dir = \"pki\"\n"),
         "t.toml:12:10: server.opcua.listen: \"127.0.0.1\": invalid socket address syntax (address:port, e.g. 127.0.0.1:4840)"),
        ("opcua: an unknown security", format!("{CARD}[server.opcua]\nlisten = \"127.0.0.1:4840\"\npki_dir = \"pki\"\nsecurity = [\"basic128rsa15\"]\n"),
         "t.toml:14:13: server.opcua.security[0]: unknown variant `basic128rsa15`, expected one of `none`, `basic256sha256_sign`, `basic256sha256_sign_encrypt`, `aes128_sha256_rsaoaep_sign`, `aes128_sha256_rsaoaep_sign_encrypt`"),
        ("opcua: a users file that is not there", format!("{CARD}[server.opcua]\nlisten = \"127.0.0.1:4840\"\npki_dir = \"pki\"\nusers_file = \"/nonexistent/users.toml\"\n"),
         "t.toml:14:14: server.opcua.users_file: \"/nonexistent/users.toml\": No such file or directory (os error 2)"),
        ("opcua: a limit out of its bounds", format!("{CARD}[server.opcua]\nlisten = \"127.0.0.1:4840\"\npki_dir = \"pki\"\n[server.opcua.limits]\nsessions = 0\n"),
         "t.toml:15:12: server.opcua.limits.sessions: 0: 1-1000 sessions"),
        ("mqtt: a TLS CA file that is not there", format!("{CARD}[server.mqtt]\nbroker = \"b:8883\"\n[server.mqtt.tls]\nca = \"/nonexistent/ca.pem\"\n[server.mqtt.json]\n"),
         "t.toml:14:6: server.mqtt.tls.ca: \"/nonexistent/ca.pem\": No such file or directory (os error 2)"),
        ("metrics: a port that is not there", format!("{CARD}[server.metrics]\nports = [\"sim0.ai.ch99\"]\n"),
         "t.toml:12:10: server.metrics.ports[0]: \"sim0.ai.ch99\": sim0.ai has no port \"ch99\"; its ports: ch0"),
        ("metrics: an address that is not one", format!("{CARD}[server.metrics]\nlisten = \"localhost\"\n"),
         "t.toml:12:10: server.metrics.listen: \"localhost\": invalid socket address (address:port, e.g. 127.0.0.1:9464)"),
        ("foxglove: nothing to stream", format!("{CARD}[server.foxglove]\n"),
         "t.toml:11:1: server.foxglove.ports: nothing to stream: list ports, or give devices = true or steps = true"),
        ("foxglove: writes without a token", format!("{CARD}[server.foxglove]\nports = [\"sim0.ai\"]\nallow_writes = true\ninputs = [\"sim0.ao.ch0\"]\n"),
         "t.toml:11:1: server.foxglove.token: allow_writes needs a token"),
        ("foxglove: an input that is an output", format!("{CARD}[server.foxglove]\nports = [\"sim0.ai\"]\nallow_writes = true\ninputs = [\"sim0.ai.ch0\"]\ntoken = \"0123456789abcdefgh\"\n"),
         "t.toml:14:11: server.foxglove.inputs[0]: \"sim0.ai.ch0\" is not an input port (component.port): hwgw set would refuse it"),
        ("foxglove: inputs without allow_writes", format!("{CARD}[server.foxglove]\nports = [\"sim0.ai.ch0\"]\ninputs = [\"sim0.ao.ch0\"]\n"),
         "t.toml:11:1: server.foxglove.allow_writes: inputs are written only with allow_writes = true"),
        ("foxglove: a port that is not there", format!("{CARD}[server.foxglove]\nports = [\"sim0.ai.ch9\"]\n"),
         "t.toml:12:10: server.foxglove.ports[0]: \"sim0.ai.ch9\": sim0.ai has no port \"ch9\"; its ports: ch0"),
        ("a server section of the wrong shape", format!("modbus_server = 5\n{CARD}"),
         "t.toml:1:17: modbus_server: invalid type: integer `5`, expected struct ServerConfig"),
        ("a server section's unknown key", format!("{CARD}[modbus_server]\nlisten = \"127.0.0.1:0\"\nport = 502\n"),
         "t.toml:13:1: modbus_server.port: unknown field `port`, expected one of `listen`, `rtu_over_tcp`, `serial`, `units`, `max_clients`, `max_clients_per_address`, `idle_timeout_s`, `frame_timeout_ms`, `write_confirm_ms`, `register`, `gateway`"),
        ("zenoh: a bad endpoint", "[zenoh]\nname = \"A\"\nlisten = [\"tcp:127.0.0.1\"]\n".into(),
         "t.toml:3:11: zenoh.listen[0]: \"tcp:127.0.0.1\" is not a Zenoh endpoint (Endpoints must be of the form <protocol>/<address>[?<metadata>][#<config>]: tcp:127.0.0.1); e.g. \"tcp/127.0.0.1:7447\""),
        ("zenoh: a transport this build lacks", "[zenoh]\nname = \"A\"\nconnect = [\"udp/127.0.0.1:7447\"]\n".into(),
         "t.toml:3:12: zenoh.connect[0]: \"udp/127.0.0.1:7447\": this build speaks tcp and tls, not \"udp\"; a router can bridge to others"),
        ("zenoh: TLS without certificates", "[zenoh]\nname = \"A\"\nlisten = [\"tls/127.0.0.1:7447\"]\n".into(),
         "t.toml:3:11: zenoh.listen[0]: \"tls/127.0.0.1:7447\" is a TLS endpoint: give [zenoh.tls] root_ca (and cert, key to listen)"),
        ("zenoh: nowhere to meet", "[zenoh]\nname = \"A\"\n".into(),
         "t.toml:1:1: zenoh.listen: nothing to listen on and nothing to connect to: give `listen` or `connect` (e.g. listen = [\"tcp/127.0.0.1:7447\"])"),
        ("zenoh: a name that cannot be a key", "[zenoh]\nname = \"a/b\"\nlisten = [\"tcp/127.0.0.1:7447\"]\n".into(),
         "t.toml:2:8: zenoh.name: \"a/b\" cannot name a gateway: use 1 to 64 letters, digits, '_' or '-'"),
        ("zenoh: an import without interfaces", "[zenoh]\nname = \"A\"\nlisten = [\"tcp/127.0.0.1:7447\"]\n[[zenoh.import]]\ngateway = \"B\"\ndevice = \"sim0\"\n".into(),
         "t.toml:4:1: zenoh.import[0]: no interface: give analog_in, analog_out, digital_in, digital_out (channel counts) or encoder = true"),
        ("zenoh: an import of too many channels", "[zenoh]\nname = \"A\"\nlisten = [\"tcp/127.0.0.1:7447\"]\n[[zenoh.import]]\ngateway = \"B\"\ndevice = \"sim0\"\nanalog_in = 100000\n".into(),
         "t.toml:7:13: zenoh.import[0].analog_in: 100000 channels: give 1 ..= 4096"),
        ("zenoh: a wildcard device", "[zenoh]\nname = \"A\"\nlisten = [\"tcp/127.0.0.1:7447\"]\n[[zenoh.import]]\ngateway = \"B\"\ndevice = \"*\"\ndigital_in = 1\n".into(),
         "t.toml:6:10: zenoh.import[0].device: \"*\" cannot be a remote device's name (no '*', '$', '?', '#', white space or empty parts)"),
        ("zenoh: stale after offline", "[zenoh]\nname = \"A\"\nlisten = [\"tcp/127.0.0.1:7447\"]\nstale_ms = 2000\noffline_ms = 1000\n".into(),
         "t.toml:4:12: zenoh.stale_ms: a device is stale (2000 ms) before it is offline (1000 ms), not after"),
        ("zenoh: an unknown key", "[zenoh]\nname = \"A\"\nlisten = [\"tcp/127.0.0.1:7447\"]\nmulticast = true\n".into(),
         "t.toml:4:1: zenoh.multicast: unknown field `multicast`, expected one of `name`, `mode`, `listen`, `connect`, `tls`, `gossip`, `publish_ms`, `stale_ms`, `offline_ms`, `lease_ms`, `request_timeout_ms`, `import`, `export`"),
        ("wrong type", "thread_scope = \"yes\"\n".into(),
         "t.toml:1:16: thread_scope: invalid type: string \"yes\", expected a boolean"),
        ("missing card name", "[[card]]\ndriver = \"sim\"\n".into(),
         "t.toml:1:1: card[0]: missing field `name`"),
        ("unknown driver", "[[card]]\nname = \"x\"\ndriver = \"canbus\"\n".into(),
         "t.toml:3:10: card[0].driver: unknown driver \"canbus\"; this build has: canopen, comedi, firmata, gpio, i2c, modbus, sim, socketcan"),
        // A CAN interface that is not here checks (the summary warns; `run` needs it).
        ("CAN interface missing", format!("{CAN}interface = \"can7\"\n"), "ok"),
        ("CANopen: interface missing", format!("{CANOPEN}[[card.canopen.node.tpdo]]\nnumber = 1\nobjects = [{{ object = \"0x6000:1\" }}]\n"), "ok"),
        ("CANopen: an object not in the EDS", format!("{CANOPEN}[[card.canopen.node.tpdo]]\nnumber = 1\nobjects = [{{ object = \"0x6001:1\" }}]\n"), 
         "t.toml:11:23: card[0].canopen.node[0].tpdo[0].objects[0].object: card \"io\": 0x6001 sub 1 is not in the node's dictionary"),
        ("CANopen: an RPDO carrying an input", format!("{CANOPEN}[[card.canopen.node.rpdo]]\nnumber = 1\nobjects = [{{ object = \"0x6000:1\" }}]\n"), 
         "t.toml:9:1: card[0].canopen.node[0].rpdo[0]: card \"io\": RPDO1: 0x6000 sub 1 (Read input 1h to 8h) is ro: an RPDO carries what it may write"),
        ("CANopen: an object written wrong", format!("{CANOPEN}[[card.canopen.node.tpdo]]\nnumber = 1\nobjects = [{{ object = \"6000.1\" }}]\n"), 
         "t.toml:11:23: card[0].canopen.node[0].tpdo[0].objects[0].object: card \"io\": \"6000.1\": expected 0xINDEX:SUB"),
        ("CANopen: a node twice", format!("{CANOPEN}[[card.canopen.node]]\nid = 5\neds = \"../drivers/canopen/tests/eds/io401.eds\"\n"), 
         "t.toml:10:6: card[0].canopen.node[1].id: card \"io\": node 5 is node[0] already"),
        ("CANopen: an EDS missing", "[[card]]\nname = \"io\"\ndriver = \"canopen\"\n[card.canopen]\ninterface = \"can7\"\n[[card.canopen.node]]\nid = 5\neds = \"nothing.eds\"\n".into(), 
         "t.toml:8:7: card[0].canopen.node[0].eds: card \"io\": nothing.eds: No such file or directory (os error 2)"),
        ("CANopen: PDO 5 without a COB-ID", format!("{CANOPEN}[[card.canopen.node.tpdo]]\nnumber = 5\nobjects = [{{ object = \"0x6000:1\" }}]\n"), 
         "t.toml:9:1: card[0].canopen.node[0].tpdo[0].cob_id: card \"io\": TPDO5 has no predefined COB-ID: give one"),
        ("CANopen: a digital object with a factor", format!("{CANOPEN}[[card.canopen.node.tpdo]]\nnumber = 1\nobjects = [{{ object = \"0x6000:1\", factor = 2.0 }}]\n"), 
         "t.toml:11:44: card[0].canopen.node[0].tpdo[0].objects[0].factor: card \"io\": a digital object has no factor or offset"),
        ("J1939: a NAME without an address", format!("{CAN}interface = \"can7\"\nj1939 = {{ name = \"0x8000000000000001\" }}\n"), 
         "t.toml:6:9: card[0].socketcan.j1939: card \"can\": a NAME needs the address to claim with it (address = …)"),
        ("J1939: a NAME that is not hex", format!("{CAN}interface = \"can7\"\nj1939 = {{ name = \"0xG1\", address = 0x80 }}\n"), 
         "t.toml:6:18: card[0].socketcan.j1939.name: NAME \"0xG1\": expected up to 16 hex digits (0x…)"),
        ("J1939: the null address", format!("{CAN}interface = \"can7\"\nj1939 = {{ name = 1, address = 0xFE }}\n"), 
         "t.toml:6:31: card[0].socketcan.j1939.address: card \"can\": 0xfe: expected a source address from 0 to 0xfd"),
        ("J1939: a source pinned on a plain frame", format!("{CAN}interface = \"can7\"\n[[card.socketcan.rx]]\nid = 0x100\nsource = 0x21\nsignal = [{{ name = \"a\", start = 0, length = 8 }}]\n"), 
         "t.toml:8:10: card[0].socketcan.rx[0].source: card \"can\": only J1939 frames have one: an extended frame on a card with a [j1939] table"),
        ("J1939: sending without an address", format!("{CAN}interface = \"can7\"\nj1939 = {{}}\n[[card.socketcan.tx]]\nid = 0x18FF4080\nextended = true\ncycle_ms = 100\nsignal = [{{ name = \"a\", start = 0, length = 8 }}]\n"), 
         "t.toml:7:1: card[0].socketcan.tx[0]: card \"can\": sending J1939 needs an address: set name and address in the [j1939] table"),
        ("J1939: a destination for a PDU2 group", format!("{CAN}interface = \"can7\"\nj1939 = {{ name = 1, address = 0x80 }}\n[[card.socketcan.tx]]\nid = 0x18FF4080\nextended = true\ndestination = 0x20\ncycle_ms = 100\nsignal = [{{ name = \"a\", start = 0, length = 8 }}]\n"), 
         "t.toml:10:15: card[0].socketcan.tx[0].destination: card \"can\": PGN 0xff40 is a PDU2 group: it is always broadcast"),
        ("J1939: the same PGN from any source twice", format!("{CAN}interface = \"can7\"\nj1939 = {{}}\n[[card.socketcan.rx]]\nid = 0x0CF00400\nextended = true\nsignal = [{{ name = \"a\", start = 0, length = 8 }}]\n[[card.socketcan.rx]]\nid = 0x18F00417\nextended = true\nsignal = [{{ name = \"b\", start = 0, length = 8 }}]\n"), 
         "t.toml:11:1: card[0].socketcan.rx[1]: card \"can\": PGN 0xf004 is already mapped as rx[0]"),
        ("J1939: a priority of 8", format!("{CAN}interface = \"can7\"\nj1939 = {{}}\n[[card.socketcan.rx]]\nid = 0x0CF00400\nextended = true\npriority = 8\nsignal = [{{ name = \"a\", start = 0, length = 8 }}]\n"), 
         "t.toml:10:12: card[0].socketcan.rx[0].priority: card \"can\": 8: a J1939 priority is 0 (highest) to 7"),
        ("J1939: a sent group of priority 1", format!("{CAN}interface = \"can7\"\nj1939 = {{ name = 1, address = 0x80 }}\n[[card.socketcan.tx]]\nid = 0x04FF4080\nextended = true\ncycle_ms = 100\nsignal = [{{ name = \"a\", start = 0, length = 8 }}]\n"), 
         "t.toml:7:1: card[0].socketcan.tx[0]: card \"can\": priority 1: the kernel sends priorities 0 and 1 only for CAP_NET_ADMIN, which hwgw's service does not have; set priority = 2 to 7"),
        ("J1939: a sent group longer than TP", format!("{CAN}interface = \"can7\"\nj1939 = {{ name = 1, address = 0x80 }}\n[[card.socketcan.tx]]\nid = 0x18FF4080\nextended = true\nlength = 2000\ncycle_ms = 100\nsignal = [{{ name = \"a\", start = 0, length = 8 }}]\n"), 
         "t.toml:10:10: card[0].socketcan.tx[0].length: card \"can\": 2000 bytes: hwgw sends J1939 groups of up to 1785 bytes (TP); longer ones (ETP) it only receives"),
        ("J1939: the transport's own PGN", format!("{CAN}interface = \"can7\"\nj1939 = {{}}\n[[card.socketcan.rx]]\nid = 0x1CECFF00\nextended = true\nsignal = [{{ name = \"a\", start = 0, length = 8 }}]\n"), 
         "t.toml:7:1: card[0].socketcan.rx[0]: card \"can\": PGN 0xec00 is the transport protocol's connection management (TP.CM): it cannot be mapped"),
        ("J1939: NAME 0", format!("{CAN}interface = \"can7\"\nj1939 = {{ name = 0, address = 0x80 }}\n"), 
         "t.toml:6:18: card[0].socketcan.j1939.name: card \"can\": NAME 0 is the kernel's \"no NAME\": give the node's NAME (J1939-81)"),
        ("ISO-TP: a separation time ISO 15765-2 cannot code", format!("{CAN}interface = \"can7\"\nisotp = [{{ name = \"ecu\", tx_id = 0x7E0, rx_id = 0x7E8, st_min_us = 150 }}]\n"), 
         "t.toml:6:68: card[0].socketcan.isotp[0].st_min_us: card \"can\": 150 µs: ISO 15765-2 codes 100 to 900 µs in steps of 100, or 1 to 127 ms"),
        ("ISO-TP: the same id both ways", format!("{CAN}interface = \"can7\"\nisotp = [{{ name = \"ecu\", tx_id = 0x7E0, rx_id = 0x7E0 }}]\n"), 
         "t.toml:6:49: card[0].socketcan.isotp[0].rx_id: card \"can\": the response id must differ from the request id"),
        ("CANopen: a drive on an IO module", format!("{CANOPEN}drive = {{ name = \"axis\" }}\n"), 
         "t.toml:9:9: card[0].canopen.node[0].drive: card \"io\": 0x6060 sub 0 is not in the node's dictionary"),
        ("CANopen: a drive without its controlword", format!("{CANOPEN}drive = {{ name = \"axis\" }}\n").replace("io401", "drive402"), 
         "t.toml:9:9: card[0].canopen.node[0].drive: card \"io\": a drive's RPDOs carry its controlword (0x6040:0) and target velocity (0x60FF:0)"),
        ("CANopen: a synchronous RPDO without SYNC", format!("{CANOPEN}[[card.canopen.node.rpdo]]\nnumber = 1\ntransmission = \"sync\"\nobjects = [{{ object = \"0x6200:1\" }}]\n"), 
         "t.toml:4:1: card[0].canopen.sync_ms: card \"io\": n5 RPDO1 is synchronous: hwgw sends it after its SYNC, so give sync_ms"),
        ("CANopen: a TPDO on a heartbeat id", format!("{CANOPEN}[[card.canopen.node.tpdo]]\nnumber = 1\ncob_id = 0x705\nobjects = [{{ object = \"0x6000:1\" }}]\n"), 
         "t.toml:6:1: card[0].canopen.node: card \"io\": n5 TPDO1's COB-ID 0x705 is node 5's heartbeat id"),
        // A message that does not parse is refused where it is mapped, not before.
        ("malformed DBC file, unmapped", format!("{CAN}interface = \"can7\"\ndbc = \"tests/data/broken.dbc\"\n"), "ok"),
        ("malformed DBC message, mapped", format!("{CAN}interface = \"can7\"\ndbc = \"tests/data/broken.dbc\"\n[[card.socketcan.rx]]\nmessage = \"Motion\"\n"),
         "t.toml:8:11: card[0].socketcan.rx[0].message: card \"can\": tests/data/broken.dbc:3: signal Speed: byte order @2: expected @1 (Intel) or @0 (Motorola)"),
        ("DBC message missing", format!("{CAN}interface = \"can7\"\ndbc = \"../drivers/can/tests/data/motion.dbc\"\n[[card.socketcan.rx]]\nmessage = \"Motoin\"\n"),
         "t.toml:8:11: card[0].socketcan.rx[0].message: card \"can\": the DBC file has no message \"Motoin\" (it has: Motion, Temps, Command, Trims)"),
        ("inline signal without a start bit", format!("{CAN}interface = \"can7\"\n[[card.socketcan.rx]]\nid = 0x100\nsignal = [{{ name = \"speed\", length = 16 }}]\n"),
         "t.toml:8:11: card[0].socketcan.rx[0].signal[0]: card \"can\": signal speed: an inline signal needs start and length"),
        ("DBC range no raw value reaches", format!("{CAN}interface = \"can7\"\ndbc = \"tests/data/unreachable.dbc\"\n[[card.socketcan.rx]]\nmessage = \"M\"\n"),
         "t.toml:7:1: card[0].socketcan.rx[0]: card \"can\": signal S: no raw value of the signal lies in its range [1000|2000]"),
        ("an encoder of resolution 0", format!("{CAN}interface = \"can7\"\n[[card.socketcan.rx]]\nid = 0x10\nlength = 2\nsignal = [{{ name = \"P\", start = 0, length = 16, as = \"encoder\", resolution = 0 }}]\n"),
         "t.toml:9:11: card[0].socketcan.rx[0].signal[0]: card \"can\": signal P: resolution 0: expected a count of steps per turn, not 0"),
        ("DBC signal given a scale", format!("{CAN}interface = \"can7\"\ndbc = \"../drivers/can/tests/data/motion.dbc\"\n[[card.socketcan.rx]]\nmessage = \"Motion\"\nsignal = [{{ name = \"Speed\", factor = 2 }}]\n"),
         "t.toml:9:11: card[0].socketcan.rx[0].signal[0]: card \"can\": signal Speed: the layout and scale of a DBC signal come from the DBC file; only as, resolution, upcounting and initial can be set here"),
        ("11-bit id too large", format!("{CAN}interface = \"can7\"\n[[card.socketcan.tx]]\nid = 0x800\ncycle_ms = 10\n"),
         "t.toml:7:6: card[0].socketcan.tx[0].id: card \"can\": 0x800 does not fit an 11-bit id (largest 0x7ff)"),
        ("unknown key in a card's thread", "[[card]]\nname = \"x\"\ndriver = \"sim\"\nthread = { prio = 3 }\n[card.sim]\n".into(),
         "t.toml:4:12: card[0].thread.prio: unknown field `prio`, expected one of `policy`, `priority`, `cpus`, `spin_us`"),
        ("unknown key in the CAN section", format!("{CAN}interface = \"can7\"\nbitrate = 500000\n"),
         "t.toml:6:1: card[0].socketcan.bitrate: unknown field `bitrate`, expected one of `interface`, `dbc`, `encoding`, `stale_after_cycles`, `link_check_ms`, `rx`, `tx`, `isotp`, `j1939`"),
        ("unknown key in a card", "[[card]]\nname = \"x\"\ndriver = \"sim\"\nperiod = 5\n[card.sim]\n".into(),
         "t.toml:4:1: card[0].period: unknown key \"period\"; a card has name, driver, period_ms, sample_period_ms, safe_analog_out, safe_digital_out_on, outputs, thread, names, faults, and its driver's section [card.sim]"),
        ("another driver's section", "[[card]]\nname = \"x\"\ndriver = \"sim\"\n[card.sim]\n[card.modbus]\nunit = 1\n".into(),
         "t.toml:5:7: card[0].modbus: card \"x\" uses driver \"sim\": a [card.modbus] section belongs to driver \"modbus\""),
        ("driver section missing", "[[card]]\nname = \"x\"\ndriver = \"sim\"\n".into(),
         "t.toml:1:1: card[0]: card \"x\" uses driver \"sim\" but has no [card.sim] section"),
        ("driver refuses its section", "[[card]]\nname = \"x\"\ndriver = \"sim\"\n[card.sim]\n[[card.sim.analog_in]]\nrange = { lowest = 5.0, highest = 1.0 }\nwaveform = { kind = \"constant\", value = 1.0 }\n".into(),
         "t.toml:6:9: card[0].sim.analog_in[0].range: card \"x\": physical range [5, 1] is invalid: needs finite lowest < highest"),
        ("unknown key in a driver section", "[[card]]\nname = \"x\"\ndriver = \"sim\"\n[card.sim]\ndigital_input = 8\n".into(),
         "t.toml:5:1: card[0].sim.digital_input: unknown field `digital_input`, expected one of `seed`, `analog_in`, `analog_out`, `digital_inputs`, `digital_outputs`, `digital_loopback`, `encoder`, `switch`, `record_capacity`"),
        ("duplicate card", format!("{CARD}{CARD}"),
         "t.toml:12:8: card[1].name: card \"sim0\" is defined twice (first as card[0])"),
        ("zero period", "[[card]]\nname = \"x\"\ndriver = \"sim\"\nperiod_ms = 0\n[card.sim]\n".into(),
         "t.toml:4:13: card[0].period_ms: 0 ms: expected a period above 0"),
        ("alias to nothing", with_card("[[alias]]\ninterface = \"digital_out\"\nname = \"ThreadScope\"\ntarget = \"sim9\"\n"),
         "t.toml:11:1: alias[0]: no DigitalOut named \"sim9\"; registered: sim0"),
        ("ThreadScope without its output", format!("thread_scope = true\n{CARD}"),
         "t.toml:1:16: thread_scope: ThreadScope is on, but no DigitalOut named \"ThreadScope\"; registered: sim0 (add an [[alias]] with interface = \"digital_out\" and name = \"ThreadScope\")"),
        ("unknown component type", with_card("[[component]]\nname = \"c\"\ntype = \"pid\"\nactivity = { type = \"non_periodic\" }\n"),
         "t.toml:13:8: component[0].type: unknown component type \"pid\"; this build has: blinker, follow, recorder, reporter, scan, script"),
        ("duplicate component", with_card("[[component]]\nname = \"c\"\ntype = \"follow\"\nactivity = { type = \"non_periodic\" }\n[[component]]\nname = \"c\"\ntype = \"follow\"\nactivity = { type = \"non_periodic\" }\n"),
         "t.toml:16:8: component[1].name: a component named \"c\" already exists"),
        ("property of the wrong type", with_card("[[component]]\nname = \"b\"\ntype = \"blinker\"\nactivity = { type = \"periodic\", period_ms = 100 }\nproperties = { device = \"sim0\", bit = \"three\" }\n"),
         "t.toml:15:14: component[0].properties: bit: expected u32: invalid type: string \"three\", expected u32"),
        ("unknown property", with_card("[[component]]\nname = \"f\"\ntype = \"follow\"\nactivity = { type = \"non_periodic\" }\nproperties = { gian = 2.0 }\n"),
         "t.toml:15:14: component[0].properties: no property \"gian\"; there are: gain, offset"),
        ("configure fails: no such device", with_card("[[component]]\nname = \"b\"\ntype = \"blinker\"\nactivity = { type = \"periodic\", period_ms = 100 }\nproperties = { device = \"sim7\", bit = 1 }\n"),
         "t.toml:11:1: component[0]: component \"b\": configure_hook failed: no DigitalOut named \"sim7\"; registered: sim0"),
        ("configure fails: no such bit", with_card("[[component]]\nname = \"b\"\ntype = \"blinker\"\nactivity = { type = \"periodic\", period_ms = 100 }\nproperties = { device = \"sim0\", bit = 8 }\n"),
         "t.toml:11:1: component[0]: component \"b\": configure_hook failed: bit 8 does not exist on \"sim0\" (8 outputs)"),
        ("connection address without a port", with_card("[[connection]]\nfrom = \"sim0\"\nto = \"sim0.ao.ch0\"\n"),
         "t.toml:12:8: connection[0].from: \"sim0\": expected \"component.port\""),
        ("connection to an unknown component", with_card("[[connection]]\nfrom = \"nope.ch0\"\nto = \"sim0.ao.ch0\"\n"),
         "t.toml:12:8: connection[0].from: no component named \"nope\"; there are: sim0, sim0.ai, sim0.ao, sim0.do"),
        ("connection to an unknown port", with_card("[[connection]]\nfrom = \"sim0.ai.ch7\"\nto = \"sim0.ao.ch0\"\n"),
         "t.toml:12:8: connection[0].from: \"sim0.ai\" has no port \"ch7\"; it has: ch0"),
        ("connection between types", with_card("[[connection]]\nfrom = \"sim0.ai.ch0\"\nto = \"sim0.do.bit0\"\n"),
         "t.toml:11:1: connection[0]: sim0.ai.ch0 -> sim0.do.bit0: cannot connect \"ch0\" (f64) to \"bit0\" (bool): the types differ"),
        ("connection from an input", with_card("[[connection]]\nfrom = \"sim0.ao.ch0\"\nto = \"sim0.ao.ch0\"\n"),
         "t.toml:11:1: connection[0]: sim0.ao.ch0 -> sim0.ao.ch0: cannot connect \"ch0\" to \"ch0\": a connection goes from an output port to an input port"),
        ("zero-size buffer", with_card("[[connection]]\nfrom = \"sim0.ai.ch0\"\nto = \"sim0.ao.ch0\"\npolicy = { kind = { type = \"buffer\", size = 0 } }\n"),
         "t.toml:11:1: connection[0]: sim0.ai.ch0 -> sim0.ao.ch0: a buffer connection needs a size of at least 1"),
        ("unknown activity type", with_card("[[component]]\nname = \"f\"\ntype = \"follow\"\nactivity = { type = \"sometimes\" }\n"),
         "t.toml:14:21: component[0].activity.type: unknown variant `sometimes`, expected one of `periodic`, `non_periodic`, `file_descriptor`, `slave`"),
        ("negative period", with_card("[[component]]\nname = \"f\"\ntype = \"follow\"\nactivity = { type = \"periodic\", period_ms = -5 }\n"),
         "t.toml:14:45: component[0].activity.period_ms: -5 ms: expected a period above 0"),
        ("too many channel names", CARD.replace("[card.sim]\n", "[card.names]\nanalog_out = [\"a\", \"b\"]\n[card.sim]\n"),
         "t.toml:5:14: card[0].names.analog_out: 2 names for 1 channels"),
        ("a channel name with a dot", CARD.replace("[card.sim]\n", "[card.names]\ndigital_out = [\"pump.1\"]\n[card.sim]\n"),
         "t.toml:5:16: card[0].names.digital_out[0]: \"pump.1\" is not a port name (no dots, no spaces, not empty)"),
        ("a channel name twice", CARD.replace("[card.sim]\n", "[card.names]\ndigital_out = [\"p\", \"p\"]\n[card.sim]\n"),
         "t.toml:5:21: card[0].names.digital_out[1]: \"p\" is used twice"),
        ("modbus section missing", "[[card]]\nname = \"plc\"\ndriver = \"modbus\"\n".into(),
         "t.toml:1:1: card[0]: card \"plc\" uses driver \"modbus\" but has no [card.modbus] section"),
        ("modbus point refused by the map", "[[card]]\nname = \"plc\"\ndriver = \"modbus\"\n[card.modbus]\ntransport = { type = \"tcp\", address = \"127.0.0.1:502\" }\n[[card.modbus.point]]\ntable = \"coils\"\naddress = 0\ntype = \"f32\"\n".into(),
         "t.toml:7:9: card[0].modbus.point[0].table: card \"plc\": coils hold single bits: no type, bit, scale or offset"),
        ("modbus timing refused", "[[card]]\nname = \"plc\"\ndriver = \"modbus\"\n[card.modbus]\ntransport = { type = \"tcp\", address = \"127.0.0.1:502\" }\npoll_ms = 0\n".into(),
         "t.toml:6:11: card[0].modbus.poll_ms: card \"plc\": 0 ms: expected a time above 0"),
        ("modbus unknown key", "[[card]]\nname = \"plc\"\ndriver = \"modbus\"\n[card.modbus]\ntransport = { type = \"tcp\", address = \"127.0.0.1:502\" }\nslave = 3\n".into(),
         "t.toml:6:1: card[0].modbus.slave: unknown field `slave`, expected one of `transport`, `unit`, `poll_ms`, `timeout_ms`, `stale_after`, `offline_after`, `backoff_max_ms`, `max_gap`, `read_back`, `point`"),
        ("served device missing", with_card("[modbus_server]\nlisten = \"127.0.0.1:0\"\n[[modbus_server.register]]\ntable = \"coils\"\naddress = 0\ndevice = \"sim9\"\ninterface = \"digital_out\"\n"),
         "t.toml:16:10: modbus_server.register[0].device: no DigitalOut named \"sim9\"; registered: sim0"),
        ("served registers overlap", with_card("[modbus_server]\nlisten = \"127.0.0.1:0\"\n[[modbus_server.register]]\ntable = \"input_registers\"\naddress = 0\ndevice = \"sim0\"\ninterface = \"analog_in\"\ntype = \"f32\"\n[[modbus_server.register]]\ntable = \"input_registers\"\naddress = 1\ndevice = \"sim0\"\ninterface = \"analog_in\"\n"),
         "t.toml:13:1: modbus_server.register: entry 1: input_registers 1 is already served by entry 0"),
        ("served: a write confirmation too short", with_card("[modbus_server]\nlisten = \"127.0.0.1:0\"\nwrite_confirm_ms = 5\n"),
         "t.toml:13:20: modbus_server.write_confirm_ms: 5: 10-60000 ms"),
        ("served: no connection per address", with_card("[modbus_server]\nlisten = \"127.0.0.1:0\"\nmax_clients_per_address = 0\n"),
         "t.toml:13:27: modbus_server.max_clients_per_address: 0: 1-1024"),
        ("served: a frame timeout past the idle timeout", with_card("[modbus_server]\nlisten = \"127.0.0.1:0\"\nidle_timeout_s = 2\nframe_timeout_ms = 3000\n"),
         "t.toml:14:20: modbus_server.frame_timeout_ms: 3000 ms: at most idle_timeout_s (2 s)"),
        ("served: nowhere to serve", with_card("[modbus_server]\nmax_clients = 4\n"),
         "t.toml:11:1: modbus_server.listen: missing: give listen (Modbus TCP), rtu_over_tcp or serial (an RTU slave): where to serve"),
        ("served: unit 0, the broadcast", with_card("[modbus_server]\nlisten = \"127.0.0.1:0\"\nunits = [1, 0]\n"),
         "t.toml:13:9: modbus_server.units: 0: expected 1 to 247 (or 255, TCP's \"this server\"); 0 is the broadcast"),
        ("served: a serial port that is not one", with_card("[modbus_server]\nserial = { device = \"/dev/null\" }\n"),
         "t.toml:12:21: modbus_server.serial.device: /dev/null is not a serial port: it is a memory device (1:3, as /dev/null and /dev/mem are)"),
        ("served: rs485 delays too long", with_card("[modbus_server]\nserial = { device = \"/dev/ttyS0\", rs485 = { delay_after_send_ms = 5000 } }\n"),
         "t.toml:12:67: modbus_server.serial.rs485.delay_after_send_ms: 5000: expected 0 to 1000 ms"),
        ("modbus rtu over tcp turnaround", "[[card]]\nname = \"plc\"\ndriver = \"modbus\"\n[card.modbus]\ntransport = { type = \"rtu_over_tcp\", address = \"127.0.0.1:502\", turnaround_ms = 20000 }\n".into(),
         "t.toml:5:81: card[0].modbus.transport.turnaround_ms: card \"plc\": 20000: expected 0 to 10000 ms"),
        ("served: a gateway without its own units", with_card("[modbus_server]\nlisten = \"127.0.0.1:0\"\n[[modbus_server.gateway]]\ntransport = { type = \"tcp\", address = \"127.0.0.1:502\" }\n"),
         "t.toml:11:1: modbus_server.units: missing: with gateway routes, give the unit ids the server answers itself (units = [] for none)"),
        ("served: a gateway to no card's line", with_card("[modbus_server]\nlisten = \"127.0.0.1:0\"\nunits = []\n[[modbus_server.gateway]]\ntransport = { type = \"tcp\", address = \"127.0.0.1:502\" }\n"),
         "t.toml:15:13: modbus_server.gateway[0].transport: no Modbus card's line goes to 127.0.0.1:502: the gateway forwards on a card's line, one request at a time with its polls (a card with no points is the line alone)"),
        ("served: a gateway on a serial port alone", "[[card]]\nname = \"plc\"\ndriver = \"modbus\"\n[card.modbus]\ntransport = { type = \"tcp\", address = \"127.0.0.1:502\" }\n[modbus_server]\nunits = [1]\nserial = { device = \"/dev/ttyS0\" }\n[[modbus_server.gateway]]\ntransport = { type = \"tcp\", address = \"127.0.0.1:502\" }\n".into(),
         "t.toml:9:1: modbus_server.gateway: a gateway forwards TCP masters' requests: give listen or rtu_over_tcp (on a serial port the other units answer themselves)"),
        ("served: a gateway route over the own units", "[[card]]\nname = \"plc\"\ndriver = \"modbus\"\n[card.modbus]\ntransport = { type = \"tcp\", address = \"127.0.0.1:502\" }\n[modbus_server]\nlisten = \"127.0.0.1:0\"\nunits = [1, 2]\n[[modbus_server.gateway]]\nunits = [2, 3]\ntransport = { type = \"tcp\", address = \"127.0.0.1:502\" }\n".into(),
         "t.toml:10:9: modbus_server.gateway[0].units: unit 2 is the server's own (units): it is never forwarded"),
        ("served: a slave on a card's line", "[[card]]\nname = \"plc\"\ndriver = \"modbus\"\n[card.modbus]\ntransport = { type = \"rtu\", device = \"/dev/ttyS0\" }\n[modbus_server]\nserial = { device = \"/dev/ttyS0\" }\n".into(),
         "t.toml:7:21: modbus_server.serial.device: /dev/ttyS0 is a Modbus card's line: one port is either hwgw's line to its units (a master) or its slave's, not both"),
        // What a hostile configuration tried (issue 12): each gets its error, none a panic,
        // a hang or an unbounded allocation.
        ("a component that wakes itself", with_card("[[component]]\nname = \"f\"\ntype = \"follow\"\nactivity = { type = \"non_periodic\" }\n[[connection]]\nfrom = \"f.out\"\nto = \"f.in\"\n"),
         "t.toml:15:1: connection[0]: f.out -> f.in: f wakes itself: each value it writes wakes it again, for ever; make it periodic or connect to a port that is not an event port"),
        ("a card period of 1e308 ms", "[[card]]\nname = \"x\"\ndriver = \"sim\"\nperiod_ms = 1e308\n[card.sim]\n".into(),
         "t.toml:4:13: card[0].period_ms: 1e308 ms: expected at most 86400000 ms (a day)"),
        ("a sample period of 0", "[[card]]\nname = \"x\"\ndriver = \"sim\"\nsample_period_ms = 0\n[card.sim]\n".into(),
         "t.toml:4:20: card[0].sample_period_ms: 0 ms: expected a period above 0"),
        ("a component period of 1e308 ms", with_card("[[component]]\nname = \"f\"\ntype = \"follow\"\nactivity = { type = \"periodic\", period_ms = 1e308 }\n"),
         "t.toml:14:45: component[0].activity.period_ms: 1e308 ms: expected at most 86400000 ms (a day)"),
        ("a Modbus poll of 1e308 ms", "[[card]]\nname = \"plc\"\ndriver = \"modbus\"\n[card.modbus]\ntransport = { type = \"tcp\", address = \"127.0.0.1:502\" }\npoll_ms = 1e308\n".into(),
         "t.toml:6:11: card[0].modbus.poll_ms: card \"plc\": 1e308 ms: expected at most 86400000 ms (a day)"),
        ("a record of 4e9 writes", "[[card]]\nname = \"x\"\ndriver = \"sim\"\n[card.sim]\nrecord_capacity = 4000000000\n".into(),
         "t.toml:5:19: card[0].sim.record_capacity: card \"x\": 4000000000: at most 1048576"),
        ("a channel group of 4294967295", "[[card]]\nname = \"x\"\ndriver = \"sim\"\n[card.sim]\n[[card.sim.analog_in]]\ncount = 4294967295\nrange = { lowest = 0.0, highest = 1.0 }\nwaveform = { kind = \"constant\", value = 0.0 }\n".into(),
         "t.toml:5:1: card[0].sim.analog_in: card \"x\": 4294967295: at most 65536"),
        ("a buffer of 4e9 samples", with_card("[[connection]]\nfrom = \"sim0.ai.ch0\"\nto = \"sim0.ao.ch0\"\npolicy = { kind = { type = \"buffer\", size = 4000000000 } }\n"),
         "t.toml:11:1: connection[0]: sim0.ai.ch0 -> sim0.ao.ch0: a buffer connection of 4000000000 samples is too large (at most 1048576)"),
        ("a u32 register at 65535", "[[card]]\nname = \"plc\"\ndriver = \"modbus\"\n[card.modbus]\ntransport = { type = \"tcp\", address = \"127.0.0.1:502\" }\n[[card.modbus.point]]\ntable = \"holding_registers\"\naddress = 65535\ntype = \"u32\"\n".into(),
         "t.toml:8:11: card[0].modbus.point[0].address: card \"plc\": 65535: a u32 point of 2 registers runs past address 65535"),
        ("a safe value out of range", CARD.replace("[card.sim]\n", "safe_analog_out = [11.0]\n[card.sim]\n"),
         "t.toml:4:20: card[0].safe_analog_out[0]: 11: not a safe value for analog output \"ch0\": value 11 is outside channel 0's range [0, 10]"),
        ("a NaN safe value", CARD.replace("[card.sim]\n", "safe_analog_out = [nan]\n[card.sim]\n"),
         "t.toml:4:20: card[0].safe_analog_out[0]: is NaN (nan): give a finite number"),
        ("a safe value of 1e308", CARD.replace("[card.sim]\n", "safe_analog_out = [1e308]\n[card.sim]\n"),
         "t.toml:4:20: card[0].safe_analog_out[0]: 1e308: not a safe value for analog output \"ch0\": value 1e308 is outside channel 0's range [0, 10]"),
        ("a safe bit that does not exist", CARD.replace("[card.sim]\n", "safe_digital_out_on = [999]\n[card.sim]\n"),
         "t.toml:4:24: card[0].safe_digital_out_on[0]: bit 999 does not exist (the card has 8 digital outputs)"),
        ("a policy for no output", CARD.replace("[card.sim]\n", "[card.outputs]\nsafe = { valve = \"keep\" }\nwatchdog_ms = 0\n[card.sim]\n"),
         "t.toml:5:18: card[0].outputs.safe.valve: the card has no output port \"valve\"; it has: ch0, bit0, bit1, bit2, bit3, bit4, bit5, bit6, bit7\nt.toml:6:15: card[0].outputs.watchdog_ms: 0: expected 1 to 86400000 ms"),
        ("a FIFO priority of 200", "[[card]]\nname = \"x\"\ndriver = \"sim\"\nthread = { policy = \"fifo\", priority = 200 }\n[card.sim]\n".into(),
         "t.toml:4:10: card[0].thread: priority 200: SCHED_FIFO takes 1 to 99"),
        ("CPU 999", with_card("[[component]]\nname = \"f\"\ntype = \"follow\"\nactivity = { type = \"periodic\", period_ms = 10, cpus = [999] }\n"),
         &*Box::leak(format!("t.toml:14:12: component[0].activity: cpu 999 does not exist (this machine has {cpus}: 0..={})", cpus - 1).into_boxed_str())),
        ("a DBC file that never ends", format!("{CAN}interface = \"can7\"\ndbc = \"/dev/zero\"\n"),
         "t.toml:6:7: card[0].socketcan.dbc: card \"can\": /dev/zero: not a regular file (a DBC file is text)"),
        ("a socket path that is a file", format!("control_socket = \"{}\"\n{CARD}", concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/broken.dbc")),
         &*Box::leak(format!("t.toml:1:18: control_socket: {}/tests/data/broken.dbc: exists and is not a socket; refusing to replace it (choose another --socket)", env!("CARGO_MANIFEST_DIR")).into_boxed_str())),
        ("control limits out of range", format!("control_clients = 0\ncontrol_idle_s = 0\n{CARD}"),
         "t.toml:1:19: control_clients: 0: expected 1 to 1024 clients\nt.toml:2:18: control_idle_s: 0 s: expected 1 to 86400 seconds"),
        ("a report nobody can write", with_card("[[component]]\nname = \"rec\"\ntype = \"reporter\"\nactivity = { type = \"periodic\", period_ms = 10 }\nproperties = { file = \"/nonexistent/r.csv\", ports = [\"sim0.ai.ch0\"] }\n"),
         "t.toml:11:1: component[0]: component \"rec\": configure_hook failed: /nonexistent/r.csv: the directory /nonexistent does not exist"),
        ("ThreadScope recordings kept: none, or too many", format!("thread_scope_vcd = \"/tmp/s.vcd\"\nthread_scope_vcd_keep = 0\n{CARD}"),
         "t.toml:2:25: thread_scope_vcd_keep: 0: expected 1 to 1000 files"),
        ("ThreadScope recordings kept of no recording", format!("thread_scope_vcd_keep = 5000\n{CARD}"),
         "t.toml:1:25: thread_scope_vcd_keep: 5000: expected 1 to 1000 files\nt.toml:1:25: thread_scope_vcd_keep: there is no thread_scope_vcd to keep files of: name one"),
        ("a ThreadScope recording in no folder", format!("thread_scope_vcd = \"/nonexistent/s.vcd\"\n{CARD}"),
         "t.toml:1:20: thread_scope_vcd: /nonexistent/s.vcd: the directory /nonexistent does not exist"),
        ("a ThreadScope recording named as a folder", format!("thread_scope_vcd = \"/tmp/\"\n{CARD}"),
         "t.toml:1:20: thread_scope_vcd: \"/tmp/\": expected a file name"),
        ("a recording of a port that does not exist", with_card(&recorder("ports = [\"sim0.ai.ch7\"], file = \"/tmp/never.mcap\"")),
         "t.toml:11:1: component[0]: component \"rec\": configure_hook failed: \"sim0.ai.ch7\": \"sim0.ai\" has no port \"ch7\"; it has: ch0"),
        ("a recording of an input port", with_card(&recorder("ports = [\"sim0.ao.ch0\"], file = \"/tmp/never.mcap\"")),
         "t.toml:11:1: component[0]: component \"rec\": configure_hook failed: \"sim0.ao.ch0\" is an input port: a recording takes output ports (outputs of sim0.ao: none)"),
        ("a recording triggered by a port it does not record", with_card(&recorder("ports = [\"sim0.ai\"], trigger = \"sim0.do.bit0 > 0\", file = \"/tmp/never.mcap\"")),
         "t.toml:11:1: component[0]: component \"rec\": configure_hook failed: trigger port \"sim0.do.bit0\" is not among the ports recorded"),
        ("a recording with a trigger that does not parse", with_card(&recorder("ports = [\"sim0.ai\"], trigger = \"sim0.ai.ch0 >> 1\", file = \"/tmp/never.mcap\"")),
         "t.toml:11:1: component[0]: component \"rec\": configure_hook failed: trigger \"sim0.ai.ch0 >> 1\": \"> 1\" is not a number (expected \"component.port OP number\", OP one of > >= < <= == !=)"),
        ("a recording over a file", with_card(&recorder(&format!("ports = [\"sim0.ai\"], file = \"{}\"", concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/broken.dbc")))),
         &*Box::leak(format!("t.toml:11:1: component[0]: component \"rec\": configure_hook failed: {}/tests/data/broken.dbc exists: it is never overwritten; remove it or name another file", env!("CARGO_MANIFEST_DIR")).into_boxed_str())),
        ("a recording of nothing", with_card(&recorder("file = \"/tmp/never.mcap\"")),
         "t.toml:11:1: component[0]: component \"rec\": configure_hook failed: properties ports and activities are empty: name what to record"),
        // NaN and the infinities, in every float key, named as what they are.
        ("zenoh: publish_ms = nan", format!("{ZENOH}publish_ms = nan\n"),
         "t.toml:4:14: zenoh.publish_ms: is NaN (nan): give a finite number"),
        ("zenoh: stale_ms = inf", format!("{ZENOH}stale_ms = inf\n"),
         "t.toml:4:12: zenoh.stale_ms: is infinite (inf): give a finite number"),
        ("zenoh: offline_ms = -inf", format!("{ZENOH}offline_ms = -inf\n"),
         "t.toml:4:14: zenoh.offline_ms: is infinite (-inf): give a finite number"),
        ("zenoh: lease_ms = nan", format!("{ZENOH}lease_ms = nan\n"),
         "t.toml:4:12: zenoh.lease_ms: is NaN (nan): give a finite number"),
        ("zenoh: request_timeout_ms = +nan", format!("{ZENOH}request_timeout_ms = +nan\n"),
         "t.toml:4:22: zenoh.request_timeout_ms: is NaN (+nan): give a finite number"),
        ("zenoh: a time of 1e308 ms", format!("{ZENOH}lease_ms = 1e308\n"),
         "t.toml:4:12: zenoh.lease_ms: 1e308 ms is outside 1 ..= 3600000 ms"),
        ("a card period of NaN", "[[card]]\nname = \"x\"\ndriver = \"sim\"\nperiod_ms = nan\n[card.sim]\n".into(),
         "t.toml:4:13: card[0].period_ms: is NaN (nan): give a finite number"),
        ("a property of NaN (not \"invalid type: null\")", with_card("[[component]]\nname = \"f\"\ntype = \"follow\"\nactivity = { type = \"non_periodic\" }\nproperties = { gain = nan, offset = -inf }\n"),
         "t.toml:15:23: component[0].properties.gain: is NaN (nan): give a finite number\nt.toml:15:37: component[0].properties.offset: is infinite (-inf): give a finite number"),
        ("a range of -inf", CARD.replace("lowest = -10.0", "lowest = -inf"),
         "t.toml:7:20: card[0].sim.analog_in[0].range.lowest: is infinite (-inf): give a finite number"),
        ("a control idle time of inf", format!("control_idle_s = inf\n{CARD}"),
         "t.toml:1:18: control_idle_s: is infinite (inf): give a finite number"),
        ("a Modbus scale of NaN", format!("{CARD}[modbus_server]\nlisten = \"127.0.0.1:0\"\n[[modbus_server.register]]\ntable = \"input_registers\"\naddress = 0\ndevice = \"sim0\"\ninterface = \"analog_in\"\nscale = nan\n"),
         "t.toml:18:9: modbus_server.register[0].scale: is NaN (nan): give a finite number"),
        // Numbers whose arithmetic overflows.
        ("a range of ±1.7e308", CARD.replace("lowest = -10.0, highest = 10.0", "lowest = -1.7e308, highest = 1.7e308"),
         "t.toml:7:9: card[0].sim.analog_in[0].range: card \"sim0\": physical range [-1.7e308, 1.7e308] is too wide: its span (highest - lowest) is infinite, beyond the largest number (about 1.8e308); narrow it"),
        ("an output range of ±1e308", CARD.replace("lowest = 0.0, highest = 10.0", "lowest = -1e308, highest = 1e308"),
         "t.toml:10:9: card[0].sim.analog_out[0].range: card \"sim0\": physical range [-1e308, 1e308] is too wide: its span (highest - lowest) is infinite, beyond the largest number (about 1.8e308); narrow it"),
        ("an encoder of 1e308 counts per unit", format!("{CARD}[[card.sim.encoder]]\nresolution = 4096\nvelocity_from = 0\ncounts_per_unit = 1e308\n"),
         "t.toml:14:19: card[0].sim.encoder[0].counts_per_unit: card \"sim0\": 1e308 counts/s per unit: over the velocity output's range [0, 10] that is more counts/s than any number; an encoder counts at most 106751991167300 counts/s (a day of motion must fit its 64-bit counter)"),
        ("an encoder of 1e14 counts per volt", format!("{CARD}[[card.sim.encoder]]\nresolution = 4096\nvelocity_from = 0\ncounts_per_unit = 1e14\n"),
         "t.toml:14:19: card[0].sim.encoder[0].counts_per_unit: card \"sim0\": 100000000000000 counts/s per unit: over the velocity output's range [0, 10] that is up to 1e15 counts/s; an encoder counts at most 106751991167300 counts/s (a day of motion must fit its 64-bit counter)"),
        ("a ramp over ±1e308", CARD.replace("waveform = { kind = \"constant\", value = 1.0 }", "waveform = { kind = \"ramp\", from = -1e308, to = 1e308, period = 1.0 }"),
         "t.toml:8:49: card[0].sim.analog_in[0].waveform.to: card \"sim0\": to - from overflows (beyond the largest number, about 1.8e308)"),
        // Paths that exist but can never work: refused from their device numbers.
        ("an I2C bus that is /dev/null", "[[card]]\nname = \"i\"\ndriver = \"i2c\"\n[card.i2c]\nbus = \"/dev/null\"\n".into(),
         "t.toml:5:7: card[0].i2c.bus: card \"i\": /dev/null is not an I2C bus: it is character device 1:3; an i2c-dev bus is a character device of major 89 (/dev/i2c-N)"),
        ("an I2C bus that is /etc/passwd", "[[card]]\nname = \"i\"\ndriver = \"i2c\"\n[card.i2c]\nbus = \"/etc/passwd\"\n".into(),
         "t.toml:5:7: card[0].i2c.bus: card \"i\": /etc/passwd is not an I2C bus: it is a regular file; an i2c-dev bus is a character device of major 89 (/dev/i2c-N)"),
        ("a PCA9685 at its all-call address", "[[card]]\nname = \"i\"\ndriver = \"i2c\"\n[card.i2c]\nbus = \"/dev/i2c-9\"\n[[card.i2c.chip]]\nmodel = \"pca9685\"\naddress = 0x70\nfrequency_hz = 200.0\nchannels = [0]\n".into(),
         "t.toml:8:11: card[0].i2c.chip[0].address: card \"i\": 0x70 is the PCA9685's LED All Call address (on by default): every PCA9685 on the bus answers it, so a chip there cannot be told from the others; give the chip's own address (0x40-0x7f by its A5..A0 pins, not 0x70)"),
        ("a Firmata port that is /dev/null", firmata("/dev/null"),
         "t.toml:5:8: card[0].firmata.port: card \"u\": /dev/null is not a serial port: it is a memory device (1:3, as /dev/null and /dev/mem are)"),
        ("a Firmata port that is /dev/tty", firmata("/dev/tty"),
         "t.toml:5:8: card[0].firmata.port: card \"u\": /dev/tty is not a serial port: it is /dev/tty, the controlling terminal (5:0)"),
        ("a Firmata port that is a file", firmata("/etc/passwd"),
         "t.toml:5:8: card[0].firmata.port: card \"u\": /etc/passwd is not a serial port: it is a regular file, not a character device"),
        ("a Modbus RTU line on /dev/zero", "[[card]]\nname = \"plc\"\ndriver = \"modbus\"\n[card.modbus]\ntransport = { type = \"rtu\", device = \"/dev/zero\", baud = 19200 }\n".into(),
         "t.toml:5:38: card[0].modbus.transport.device: card \"plc\": /dev/zero is not a serial port: it is a memory device (1:5, as /dev/null and /dev/mem are)"),
        // An unplugged board is looked for at run: its port may be absent at check.
        ("a Firmata port not plugged in", firmata("/nonexistent/ttyACM0"), "ok"),
        ("a GPIO chip that is /dev/null", gpio("/dev/null"),
         "t.toml:7:8: card[0].gpio.input[0].line: card \"g\": /dev/null: not a GPIO character device: it is character device 1:3, which no GPIO chip has (a GPIO chip is /dev/gpiochipN)"),
        ("a GPIO chip that is a file", gpio("/etc/passwd"),
         "t.toml:7:8: card[0].gpio.input[0].line: card \"g\": /etc/passwd: not a GPIO character device: it is a regular file"),
        // Zenoh endpoints that cannot be reached.
        ("zenoh: an IPv4 address that is none", "[zenoh]\nname = \"A\"\nconnect = [\"tcp/999.1.1.1:7447\"]\n".into(),
         "t.toml:3:12: zenoh.connect[0]: \"tcp/999.1.1.1:7447\": 999.1.1.1 is not an IPv4 address (four numbers 0 to 255, e.g. 127.0.0.1)"),
        ("zenoh: port 99999", "[zenoh]\nname = \"A\"\nlisten = [\"tcp/127.0.0.1:99999\"]\n".into(),
         "t.toml:3:11: zenoh.listen[0]: \"tcp/127.0.0.1:99999\": port 99999: expected 0 to 65535"),
        ("zenoh: connect to port 0", "[zenoh]\nname = \"A\"\nconnect = [\"tcp/127.0.0.1:0\"]\n".into(),
         "t.toml:3:12: zenoh.connect[0]: \"tcp/127.0.0.1:0\": port 0: expected 1 to 65535"),
        ("zenoh: a host that does not resolve", "[zenoh]\nname = \"A\"\nconnect = [\"tcp/nosuchhost.invalid:7447\"]\n".into(),
         "t.toml:3:12: zenoh.connect[0]: \"tcp/nosuchhost.invalid:7447\": host nosuchhost.invalid does not resolve: Name or service not known"),
        ("zenoh: an IPv6 address without brackets", "[zenoh]\nname = \"A\"\nconnect = [\"tcp/::1:7447\"]\n".into(),
         "t.toml:3:12: zenoh.connect[0]: \"tcp/::1:7447\": an IPv6 address is written in brackets before the port: [::1]:port"),
        ("zenoh: localhost and [::1] are fine", "[zenoh]\nname = \"A\"\nlisten = [\"tcp/[::1]:0\"]\nconnect = [\"tcp/localhost:7447\"]\n".into(), "ok"),
        // What the build refuses across components.
        ("a recorder of buffer 0", with_card(&recorder("ports = [\"sim0.ai\"], file = \"/tmp/never.mcap\", buffer = 0")),
         "t.toml:11:1: component[0]: component \"rec\": configure_hook failed: buffer 0: expected 1 to 65536 samples a port may hold"),
        ("two recorders writing one file", with_card(&format!("{}{}", recorder("ports = [\"sim0.ai\"], file = \"/tmp/never.mcap\""), recorder("ports = [\"sim0.ai\"], file = \"/tmp/./never.mcap\"").replace("\"rec\"", "\"rec2\""))),
         "t.toml:20:44: component[1].properties.file: /tmp/./never.mcap is the file of recorder \"rec\" (component[0].properties.file) too: give each its own file"),
        ("a report into a recording", with_card(&format!("{}[[component]]\nname = \"rep\"\ntype = \"reporter\"\nactivity = {{ type = \"periodic\", period_ms = 20 }}\nproperties = {{ ports = [\"sim0.ai.ch0\"], file = \"/tmp/never.mcap\" }}\n", recorder("ports = [\"sim0.ai\"], file = \"/tmp/never.mcap\""))),
         "t.toml:20:48: component[1].properties.file: /tmp/never.mcap is the file of recorder \"rec\" (component[0].properties.file) too: give each its own file"),
        ("a ThreadScope recording into a recorder's file", format!("thread_scope_vcd = \"/tmp/never.mcap\"\n{}", with_card(&recorder("ports = [\"sim0.ai\"], file = \"/tmp/never.mcap\""))),
         "t.toml:16:44: component[0].properties.file: /tmp/never.mcap is the ThreadScope recording (thread_scope_vcd) too: give each its own file"),
        ("a Modbus server of channel 99 of 2", CARD.replace("[[card.sim.analog_in]]\n", "[[card.sim.analog_in]]\ncount = 2\n") + "[modbus_server]\nlisten = \"127.0.0.1:0\"\n[[modbus_server.register]]\ntable = \"input_registers\"\naddress = 0\ndevice = \"sim0\"\ninterface = \"analog_in\"\nchannel = 99\n",
         "t.toml:19:11: modbus_server.register[0].channel: channel 99 does not exist: \"sim0\" has 2 analog inputs: 0..=1"),
        ("a Modbus server of digital output 8 of 8", format!("{CARD}[modbus_server]\nlisten = \"127.0.0.1:0\"\n[[modbus_server.register]]\ntable = \"coils\"\naddress = 0\ndevice = \"sim0\"\ninterface = \"digital_out\"\nchannel = 8\n"),
         "t.toml:18:11: modbus_server.register[0].channel: channel 8 does not exist: \"sim0\" has 8 digital outputs: 0..=7"),
        ("a served scale that overflows", format!("{CARD}[modbus_server]\nlisten = \"127.0.0.1:0\"\n[[modbus_server.register]]\ntable = \"holding_registers\"\naddress = 0\ndevice = \"sim0\"\ninterface = \"analog_out\"\nscale = 1e308\n"),
         "t.toml:18:9: modbus_server.register[0].scale: scale 1e308 and offset 0 overflow: a u16 register's largest value, 65535, times the scale plus the offset is beyond the largest number (about 1.8e308)"),
        // Error text: numbers short, long strings cut, no Rust Debug text.
        ("a count of 1e308", "control_clients = 1e308\n".into(),
         "t.toml:1:19: control_clients: invalid type: floating point `1e308`, expected u32"),
        ("an idle time of 1e308", "control_idle_s = 1e308\n".into(),
         "t.toml:1:18: control_idle_s: 1e308 s: expected 1 to 86400 seconds"),
        ("a 10 MB string", format!("thread_scope = \"{}\"\n", "x".repeat(10_000_000)),
         &*Box::leak(format!("t.toml:1:16: thread_scope: invalid type: string \"{}…\" (10000000 characters), expected a boolean", "x".repeat(80)).into_boxed_str())),
        ("a 10 MB driver name", format!("[[card]]\nname = \"x\"\ndriver = \"{}\"\n", "d".repeat(10_000_000)),
         &*Box::leak(format!("t.toml:3:10: card[0].driver: unknown driver \"{}…\" (10000000 characters); this build has: canopen, comedi, firmata, gpio, i2c, modbus, sim, socketcan", "d".repeat(80)).into_boxed_str())),
        ("a 10 MB key", format!("[[alias]]\n{} = 1\n", "k".repeat(10_000_000)),
         &*Box::leak(format!("t.toml:2:1: alias[0].{}… (10000009 characters): unknown field `{k}…` (10000000 characters), expected one of `interface`, `name`, `target`", "k".repeat(71), k = "k".repeat(80)).into_boxed_str())),
        ("an initial value outside the range (no Debug text)", CARD.replace("range = { lowest = 0.0, highest = 10.0 }", "range = { lowest = 0.0, highest = 10.0, unit = \"V\" }\ninitial = 11.0"),
         "t.toml:11:11: card[0].sim.analog_out[0].initial: card \"sim0\": 11 is outside the range [0, 10] V"),
        ("a unit of 10 MB", CARD.replace("range = { lowest = 0.0, highest = 10.0 }", &format!("range = {{ lowest = 0.0, highest = 10.0, unit = \"{}\" }}", "u".repeat(10_000_000))),
         &*Box::leak(format!("t.toml:10:9: card[0].sim.analog_out[0].range: card \"sim0\": unit \"{}…\" (10000000 characters) is longer than 23 bytes", "u".repeat(80)).into_boxed_str())),
        // Logical devices: located in their entry, the drive checked against its card's
        // output policy.
        ("a drive its card would leave on", with_card("[card.outputs]\nsafe = { bit0 = \"keep\" }\n[[logical]]\nname = \"d\"\ntype = \"drive\"\nsetpoint = { device = \"sim0\", channel = 0 }\nvolts_per_unit = 1.0\nenable = { device = \"sim0\", bit = 0 }\n"),
         "t.toml:16:12: logical[0].setpoint: the setpoint sim0.ch0: at stop the card puts it back to its value before hwgw first wrote it (\"initial\": a value hwgw does not know, or the last one written where the card cannot tell); a drive's setpoint needs its zero-velocity value as its safe value ([card.outputs] safe = { ch0 = 0.0 })\n\
          t.toml:18:10: logical[0].enable: the enable output sim0.bit0: at stop the card keeps it as it is; a drive's enable needs its off value as its safe value ([card.outputs] safe = { bit0 = false })"),
        ("an axis over a drive that does not exist", with_card("[[logical]]\nname = \"a\"\ntype = \"axis\"\ndrive = \"d\"\nencoder = \"sim0.encoder0\"\ncounts_per_unit = 1.0\n"),
         "t.toml:14:9: logical[0].drive: no Drive named \"d\"; registered: none"),
        ("a sensor over an encoder without counts", with_card("[[logical]]\nname = \"s\"\ntype = \"sensor\"\nencoder = \"sim0.encoder0\"\n"),
         "t.toml:11:1: logical[0]: a sensor over an encoder needs counts_per_unit"),
        ("a logical device of no known type", with_card("[[logical]]\nname = \"s\"\ntype = \"motor\"\n"),
         "t.toml:13:8: logical[0].type: unknown variant `motor`, expected one of `sensor`, `drive`, `axis`"),
        ("a drive's setpoint on a channel the card lacks", with_card("[[logical]]\nname = \"d\"\ntype = \"drive\"\nsetpoint = { device = \"sim0\", channel = 3 }\nvolts_per_unit = 1.0\n"),
         "t.toml:14:41: logical[0].setpoint.channel: channel 3 does not exist (the device has 1 channels: 0..=0)"),
        ("not TOML", "[[card]\nname = \"x\"\n".into(),
         "t.toml:1:8: unclosed array table, expected `]`"),
    ];
    assert!(cases.len() >= 15);
    let _ = cpus;
    let mut failures = Vec::new();
    for (what, text, want) in &cases {
        let got = errors(text);
        if got != *want {
            failures.push(format!("{what}:\n  got:  {got}\n  want: {want}"));
        }
    }
    assert!(
        failures.is_empty(),
        "{} of {} cases differ:\n{}",
        failures.len(),
        cases.len(),
        failures.join("\n")
    );
}

#[test]
fn the_shipped_examples_are_valid() {
    assert_eq!(errors(hwgw::DEMO), "ok");
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../config");
    let mut checked = 0;
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "toml") {
            let text = std::fs::read_to_string(&path).unwrap();
            let file = path.display().to_string();
            let got = errors_in(&text, &file);
            if path.ends_with("can.toml") {
                // This host has no CAN interfaces: the deployment checks all the same (the
                // interface is for `hwgw run` to find; the summary warns of it, and
                // gateway/tests/kernel_can.rs runs it for real in the kernel rig).
                assert_eq!(got, "ok", "{file}");
            } else if path.ends_with("gpio.toml") {
                // Nor GPIO chips: its chip is not found, and nothing else is wrong
                // (gateway/tests/kernel_gpio.rs runs it on gpio-sim in the kernel rig).
                assert_eq!(
                    got,
                    format!(
                        "{file}:38:8: card[0].gpio.input[0].line: card \"gpio\": no GPIO chip \
                         named or labelled \"hwgw-demo\"; there are no GPIO chips"
                    ),
                );
            } else if path.ends_with("i2c.toml") {
                // Nor I2C adapters: its bus is not found, and so the connections to the
                // card's components; nothing else may (gateway/tests/kernel_i2c.rs runs it
                // on i2c-stub in the kernel rig).
                let mut lines = got.lines();
                assert_eq!(
                    lines.next(),
                    Some(
                        format!(
                            "{file}:38:7: card[0].i2c.bus: card \"i2c\": no I2C adapter is \
                             named \"SMBus stub driver\"; there are none (is i2c-dev loaded?)"
                        )
                        .as_str()
                    ),
                    "{got}"
                );
                assert!(
                    lines.all(|l| l.contains("no component named \"i2c.a")),
                    "{got}"
                );
            } else if path.ends_with("comedi.toml") {
                // Nor comedi: neither board is found, and so ThreadScope's alias to the
                // port; nothing else may (gateway/tests/kernel_comedi.rs runs it on
                // comedi_test and comedi_parport in the kernel rig).
                let lines: Vec<&str> = got.lines().collect();
                for (i, (card, dev)) in [("daq", 0), ("lpt", 1)].iter().enumerate() {
                    assert!(
                        lines[i].contains(&format!(
                            "card[{i}].comedi.device: card \"{card}\": comedi_open on /dev/comedi{dev}: "
                        )) && lines[i].ends_with("comedi devices here: none (is the comedi module loaded?)"),
                        "{got}"
                    );
                }
                assert!(
                    lines[2].contains("alias[0]: no DigitalOut named \"lpt\""),
                    "{got}"
                );
                assert!(
                    lines[3].contains("thread_scope: ThreadScope is on"),
                    "{got}"
                );
                assert_eq!(lines.len(), 4, "{got}");
            } else {
                assert_eq!(got, "ok", "{file}");
            }
            checked += 1;
        }
    }
    assert!(checked >= 2, "config/ ships the demo and the example");
    let on_disk =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../config/demo.toml"))
            .unwrap_or_default();
    assert_eq!(
        on_disk,
        hwgw::DEMO,
        "config/demo.toml is the embedded default"
    );
}

/// What depends on the machine's files: the control socket in a folder of the test's own
/// (a socket folder must be this user's), and comedi's list of the boards it has.
#[test]
fn files_one_writer_each_and_devices_of_the_wrong_kind() {
    let dir = testkit::TempDir::new("config-errors-files");
    let sock = dir.path().join("hwgw.sock");
    let sock = sock.display();
    let text = format!("control_socket = \"{sock}\"\nthread_scope_vcd = \"{sock}\"\n{CARD}");
    assert_eq!(
        errors(&text),
        format!(
            "t.toml:2:20: thread_scope_vcd: {sock} is the control socket (control_socket) too: \
             give each its own file"
        )
    );
    // Relative to the deployment's folder, the same file.
    let file = dir.path().join("d.toml").display().to_string();
    let text = format!("control_socket = \"{sock}\"\nthread_scope_vcd = \"hwgw.sock\"\n{CARD}");
    assert_eq!(
        errors_in(&text, &file),
        format!(
            "{file}:2:20: thread_scope_vcd: {sock} is the control socket (control_socket) too: \
             give each its own file"
        )
    );
    let text = format!(
        "thread_scope_vcd = \"{sock}\"\n{}",
        with_card(&recorder(&format!(
            "ports = [\"sim0.ai\"], file = \"{sock}\""
        )))
    );
    assert_eq!(
        errors(&text),
        format!(
            "t.toml:16:44: component[0].properties.file: {sock} is the ThreadScope recording \
             (thread_scope_vcd) too: give each its own file"
        )
    );
    // Each run records into a new numbered file of thread_scope_vcd: those are its too.
    let vcd = dir.path().join("threads.vcd").display().to_string();
    let numbered = dir.path().join("threads-2.vcd").display().to_string();
    let text = format!(
        "thread_scope_vcd = \"{vcd}\"\n{}",
        with_card(&recorder(&format!(
            "ports = [\"sim0.ai\"], file = \"{numbered}\""
        )))
    );
    assert_eq!(
        errors(&text),
        format!(
            "t.toml:16:44: component[0].properties.file: {numbered} is one of the numbered files \
             ({}, …) of the ThreadScope recording (thread_scope_vcd): give each its own file",
            dir.path().join("threads-1.vcd").display()
        )
    );
    let text = format!("control_socket = \"{numbered}\"\nthread_scope_vcd = \"{vcd}\"\n{CARD}");
    assert_eq!(
        errors(&text),
        format!(
            "t.toml:2:20: thread_scope_vcd: the control socket (control_socket), {numbered}, is \
             one of the numbered files this names ({}, …): give each its own file",
            dir.path().join("threads-1.vcd").display()
        )
    );
    // Not one of them: threads-02.vcd, threads-2.vcd.bak, another folder's.
    for other in [
        "threads-02.vcd",
        "threads-2.vcd.bak",
        "threads.vcd.d/threads-2.vcd",
    ] {
        let text = format!(
            "thread_scope_vcd = \"{vcd}\"\n{}",
            with_card(&recorder(&format!(
                "ports = [\"sim0.ai\"], file = \"{}\"",
                dir.path().join(other).display()
            )))
        );
        assert!(!errors(&text).contains("numbered"), "{other}");
    }
    // A comedi device that is /dev/null: named for what it is, whether comedi is loaded
    // (its boards then listed) or not.
    let got = errors(
        "[[card]]\nname = \"c\"\ndriver = \"comedi\"\n[card.comedi]\ndevice = \"/dev/null\"\nanalog_in = [{}]\n",
    );
    assert!(
        got.starts_with(
            "t.toml:5:10: card[0].comedi.device: card \"c\": comedi_open on /dev/null: not a \
             comedi device: it is character device 1:3 (comedi's are character devices of major \
             98, /dev/comediN) (errno 19); comedi devices here: "
        ) && !got.contains('\n'),
        "{got}"
    );
}

/// A `[zenoh]` section that checks, for one more key.
const ZENOH: &str = "[zenoh]\nname = \"A\"\nlisten = [\"tcp/127.0.0.1:7447\"]\n";

/// A Firmata card `u` on `port`.
fn firmata(port: &str) -> String {
    format!(
        "[[card]]\nname = \"u\"\ndriver = \"firmata\"\n[card.firmata]\nport = \"{port}\"\ndigital_in = [{{ pin = 2 }}]\n"
    )
}

/// A GPIO card `g` on chip `chip`.
fn gpio(chip: &str) -> String {
    format!(
        "[[card]]\nname = \"g\"\ndriver = \"gpio\"\n[card.gpio]\nchip = \"{chip}\"\n[[card.gpio.input]]\nline = 0\n"
    )
}

/// A `recorder` component with `properties`.
fn recorder(properties: &str) -> String {
    format!(
        "[[component]]\nname = \"rec\"\ntype = \"recorder\"\nactivity = {{ type = \"periodic\", period_ms = 20 }}\nproperties = {{ {properties} }}\n"
    )
}

//! The script component's operations: the root machine's (`request_state`, `in_state`,
//! `get_state`, `emit`, and the `machine` service: `activate`, `start`, `stop`, `pause`,
//! `step`, `reactive`, `reset`, `deactivate`, `is_*`), the programs' (`program` service:
//! `start`, `pause`, `step`, `stop`, `is_running`, `is_paused`, `in_error`, `error_of`,
//! `list`), and `reload_script`. All run in the component's own thread, between steps.

use rtt::component::{IntrospectError, SelfRef};
use rtt::{InterfaceBuilder, TaskState};
use serde_json::Value;
use std::sync::{Arc, Mutex};

type Answer = Result<Value, String>;

/// What the operations call: the script's glue functions (`__hwgw_machine`,
/// `__hwgw_program`), run in the component's thread within its step budget.
pub trait Glue: Send + 'static {
    /// Calls glue function `name` with an operation's name and argument.
    fn glue(&mut self, name: &str, args: (String, Option<String>)) -> Answer;
}

/// Declares the operations on the component's interface.
pub fn declare<Script: Glue>(
    iface: &mut InterfaceBuilder<Script>,
    reload: &Reload,
) -> Result<(), IntrospectError> {
    let state = [("state", "a state of the root machine")];
    iface.own_operation(
        "request_state",
        "moves the root machine to a state its current state may go to now (manual L3370)",
        &state,
        |s: &mut Script, (name,): (String,)| -> Answer {
            s.glue("__hwgw_machine", ("request_state".into(), Some(name)))
                .map(|_| Value::Bool(true))
        },
    )?;
    iface.own_operation(
        "in_state",
        "whether the root machine is in a state",
        &state,
        |s: &mut Script, (name,): (String,)| -> Answer {
            s.glue("__hwgw_machine", ("in_state".into(), Some(name)))
        },
    )?;
    iface.own_operation(
        "get_state",
        "the root machine's state",
        &[],
        |s: &mut Script, (): ()| -> Answer { s.glue("__hwgw_machine", ("get_state".into(), None)) },
    )?;
    iface.own_operation(
        "emit",
        "queues an event for the root machine's event transitions",
        &[("event", "the event's name")],
        |s: &mut Script, (event,): (String,)| -> Answer {
            s.glue("__hwgw_machine", ("emit".into(), Some(event)))
        },
    )?;
    let me = reload.clone();
    iface.client_operation(
        "reload_script",
        "loads the script file again while the component is stopped; a script that fails \
         to load leaves the old one in place and says why",
        &[],
        move |(): ()| -> Answer { reload_script(&me) },
    )?;
    let mut machine = iface.provides("machine");
    for (op, doc) in [
        ("activate", "enters the initial state, reactive"),
        ("start", "automatic mode (activates first)"),
        ("stop", "to the final state, reactive"),
        ("pause", "holds the machine"),
        ("step", "one transition (or handle) in reactive mode"),
        ("reactive", "back to reactive mode"),
        ("reset", "from the final state back to the initial one"),
        ("deactivate", "leaves the machine inactive"),
        ("is_active", "whether it is active"),
        ("is_running", "whether it is in automatic mode"),
        ("is_reactive", "whether it waits for requests and events"),
        ("is_paused", "whether it is paused"),
    ] {
        machine.own_operation(op, doc, &[], move |s: &mut Script, (): ()| -> Answer {
            s.glue("__hwgw_machine", (op.into(), None))
        })?;
    }
    let mut program = iface.provides("program");
    let name = [("name", "the program's name")];
    for (op, doc) in [
        ("start", "starts (or resumes) the program"),
        ("pause", "pauses it"),
        ("step", "runs a paused program one step"),
        ("stop", "stops it"),
        ("is_running", "whether it runs"),
        ("is_paused", "whether it is paused"),
        ("in_error", "whether it stopped on an error"),
        ("error_of", "the error it stopped on"),
    ] {
        program.own_operation(
            op,
            doc,
            &name,
            move |s: &mut Script, (n,): (String,)| -> Answer {
                s.glue("__hwgw_program", (op.into(), Some(n)))
            },
        )?;
    }
    program.own_operation(
        "list",
        "the programs",
        &[],
        |s: &mut Script, (): ()| -> Answer { s.glue("__hwgw_program", ("list".into(), None)) },
    )?;
    Ok(())
}

/// What `reload_script` reaches its component by: its name and itself, once configured.
pub type Reload = Arc<Mutex<Option<(String, SelfRef)>>>;

/// Configures the stopped component again: its configure hook loads the file afresh and
/// keeps the old script when the new one fails.
fn reload_script(me: &Reload) -> Answer {
    let Some((name, me)) = rtt::lock(me).clone() else {
        return Err("not configured yet: configure loads the script".into());
    };
    let task = me.task().ok_or_else(|| format!("{name:?} is gone"))?;
    match task.state() {
        TaskState::Stopped => {}
        TaskState::PreOperational => {
            return Err("not configured: configure loads the script".into());
        }
        s => return Err(format!("{name:?} is {s:?}: stop it, then reload_script")),
    }
    task.configure()
        .map_err(|e| format!("{e} (the loaded script stays)"))?;
    Ok(Value::Bool(true))
}

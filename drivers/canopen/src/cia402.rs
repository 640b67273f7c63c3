//! The CiA 402 drive state machine (IEC 61800-7-201): the state a statusword shows, and
//! the controlword that moves a drive one transition towards what hwgw wants of it —
//! enabled (operation enabled), or disabled (ready to switch on, the power stage off),
//! a fault reset by a rising edge of controlword bit 7 on the way.

/// The states of the CiA 402 state machine, from the statusword.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum State {
    /// Not ready to switch on (initialising).
    NotReadyToSwitchOn,
    /// Switch on disabled.
    SwitchOnDisabled,
    /// Ready to switch on.
    ReadyToSwitchOn,
    /// Switched on.
    SwitchedOn,
    /// Operation enabled: the drive follows its setpoint.
    OperationEnabled,
    /// Quick stop active.
    QuickStopActive,
    /// Fault reaction active.
    FaultReactionActive,
    /// Fault.
    Fault,
}

/// The state statusword `sw` shows (bits 0-3, 5, 6 as CiA 402's table reads them).
pub fn state(sw: u16) -> State {
    match (sw & 0x4F, sw & 0x6F) {
        (0x00, _) => State::NotReadyToSwitchOn,
        (0x40, _) => State::SwitchOnDisabled,
        (_, 0x21) => State::ReadyToSwitchOn,
        (_, 0x23) => State::SwitchedOn,
        (_, 0x27) => State::OperationEnabled,
        (_, 0x07) => State::QuickStopActive,
        (0x0F, _) => State::FaultReactionActive,
        (0x08, _) => State::Fault,
        // A combination the table does not have: treated as not ready.
        _ => State::NotReadyToSwitchOn,
    }
}

/// Controlword commands.
pub mod command {
    /// Shutdown (to ready to switch on).
    pub const SHUTDOWN: u16 = 0x06;
    /// Switch on (to switched on).
    pub const SWITCH_ON: u16 = 0x07;
    /// Enable operation (switch on and enable: to operation enabled).
    pub const ENABLE_OPERATION: u16 = 0x0F;
    /// Disable voltage (to switch on disabled).
    pub const DISABLE_VOLTAGE: u16 = 0x00;
    /// Fault reset (its rising edge).
    pub const FAULT_RESET: u16 = 0x80;
    /// Quick stop (from operation enabled to quick stop active; the drive brakes on its
    /// quick-stop ramp, and by its option code stays there or goes on to switch on
    /// disabled).
    pub const QUICK_STOP: u16 = 0x02;
}

/// The controlword that moves a drive in `state` towards enabled (`enable`) or disabled;
/// `last` is the controlword sent before (a fault reset needs a rising edge of bit 7).
pub fn controlword(state: State, enable: bool, last: u16) -> u16 {
    use command::*;
    match (state, enable) {
        (State::Fault, _) => {
            if last & FAULT_RESET == 0 {
                FAULT_RESET
            } else {
                DISABLE_VOLTAGE
            }
        }
        (State::FaultReactionActive | State::NotReadyToSwitchOn, _) => DISABLE_VOLTAGE,
        (State::QuickStopActive, _) => DISABLE_VOLTAGE,
        (State::SwitchOnDisabled, _) => SHUTDOWN,
        (State::ReadyToSwitchOn, true) => SWITCH_ON,
        (State::SwitchedOn | State::OperationEnabled, true) => ENABLE_OPERATION,
        (State::ReadyToSwitchOn | State::SwitchedOn | State::OperationEnabled, false) => SHUTDOWN,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The transitions of CiA 402's state diagram a drive makes on each command, as a
    /// drive applies them (the test's own model of a drive).
    fn drive(state: State, cw: u16, last: u16) -> State {
        use State::*;
        if cw & 0x80 != 0 && last & 0x80 == 0 && state == Fault {
            return SwitchOnDisabled; // 15
        }
        match (state, cw & 0x8F) {
            (SwitchOnDisabled, 0x06) => ReadyToSwitchOn, // 2
            (ReadyToSwitchOn, 0x07) => SwitchedOn,       // 3
            (ReadyToSwitchOn | SwitchedOn, 0x0F) => OperationEnabled, // 3+4
            (SwitchedOn | OperationEnabled, 0x06) => ReadyToSwitchOn, // 6, 8
            (OperationEnabled, 0x07) => SwitchedOn,      // 5
            (ReadyToSwitchOn | SwitchedOn | OperationEnabled, 0x00) => SwitchOnDisabled, // 7, 10, 9
            (OperationEnabled, 0x02) => QuickStopActive, // 11
            (QuickStopActive, 0x00) => SwitchOnDisabled, // 12
            (s, _) => s,
        }
    }

    fn statusword(s: State) -> u16 {
        match s {
            State::NotReadyToSwitchOn => 0x00,
            State::SwitchOnDisabled => 0x40,
            State::ReadyToSwitchOn => 0x21,
            State::SwitchedOn => 0x23,
            State::OperationEnabled => 0x27,
            State::QuickStopActive => 0x07,
            State::FaultReactionActive => 0x0F,
            State::Fault => 0x08,
        }
    }

    #[test]
    fn statuswords_read_as_the_table_says_whatever_the_other_bits() {
        for s in [
            State::NotReadyToSwitchOn,
            State::SwitchOnDisabled,
            State::ReadyToSwitchOn,
            State::SwitchedOn,
            State::OperationEnabled,
            State::QuickStopActive,
            State::FaultReactionActive,
            State::Fault,
        ] {
            // Voltage enabled, warning, remote, target reached, … do not change the state.
            for noise in [0u16, 0x0010, 0x0080, 0x0200, 0x0400, 0xFE90] {
                assert_eq!(state(statusword(s) | noise), s, "{s:?} {noise:#x}");
            }
        }
    }

    #[test]
    fn every_state_reaches_enabled_and_disabled() {
        for start in [
            State::SwitchOnDisabled,
            State::ReadyToSwitchOn,
            State::SwitchedOn,
            State::OperationEnabled,
            State::QuickStopActive,
            State::Fault,
        ] {
            for (enable, goal) in [
                (true, State::OperationEnabled),
                (false, State::ReadyToSwitchOn),
            ] {
                let (mut s, mut last) = (start, 0u16);
                for _ in 0..6 {
                    let cw = controlword(state(statusword(s)), enable, last);
                    s = drive(s, cw, last);
                    last = cw;
                }
                assert_eq!(s, goal, "from {start:?} enable={enable}");
            }
        }
    }

    #[test]
    fn a_quick_stop_holds_until_disabled() {
        let s = drive(
            State::OperationEnabled,
            command::QUICK_STOP,
            command::ENABLE_OPERATION,
        );
        assert_eq!(s, State::QuickStopActive);
        assert_eq!(drive(s, command::QUICK_STOP, command::QUICK_STOP), s);
        assert_eq!(
            controlword(s, false, command::QUICK_STOP),
            command::DISABLE_VOLTAGE
        );
    }
}

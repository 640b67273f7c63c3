//! `type = "recorder"`: a component that records ports and activity steps into an MCAP
//! file for as long as it runs, or the window around a trigger.
//!
//! Give it a SCHED_OTHER periodic activity (file I/O blocks; 10–50 ms suits most): the
//! recorded components never wait for it — their samples wait in stamped buffers of
//! `buffer` samples each, and whatever does not fit is counted in the file's metadata.

use super::taps::{Taps, now_ns, resolve, wall_offset};
use recording::{Capture, Options, Recorder, Trigger, Window};
use rtt::component::IntrospectError;
use rtt::port::OutputPort;
use rtt::property::Property;
use rtt::{Component, Context, HookError, HookResult, InterfaceBuilder};
use std::path::Path;

/// Records ports and steps into an MCAP file (see the module).
pub struct McapRecorder {
    ports: Property<Vec<String>>,
    activities: Property<Vec<String>>,
    file: Property<String>,
    buffer: Property<u32>,
    max_mb: Property<u64>,
    trigger: Property<String>,
    pre_ms: Property<f64>,
    post_ms: Property<f64>,
    taps: Option<Taps>,
    capture: Option<Capture>,
    items: Vec<recording::Item>,
    written: OutputPort<u64>,
}

/// The largest file a recorder may be given, MiB (1 TiB).
const MAX_MB: u64 = 1 << 20;

impl McapRecorder {
    pub(crate) fn new(iface: &mut InterfaceBuilder<McapRecorder>) -> Result<Self, IntrospectError> {
        let p = iface.properties();
        Ok(McapRecorder {
            ports: p.add(
                "ports",
                Vec::new(),
                "output ports to record: \"component.port\", or \"component\" for all its outputs",
            )?,
            activities: p.add(
                "activities",
                Vec::new(),
                "components whose activity steps (start, end, lateness) to record",
            )?,
            file: p.add(
                "file",
                String::new(),
                "the MCAP file, created at start (an existing file is never overwritten)",
            )?,
            buffer: p.add(
                "buffer",
                4096u32,
                "samples each port may hold before the recorder takes them (more are counted as lost)",
            )?,
            max_mb: p.add("max_mb", 1024u64, "the file stops growing at this size, MiB")?,
            trigger: p.add(
                "trigger",
                String::new(),
                "record only the window around \"component.port OP number\" becoming true",
            )?,
            pre_ms: p.add("pre_ms", 200.0, "with a trigger: ms kept before it")?,
            post_ms: p.add("post_ms", 1000.0, "with a trigger: ms recorded after it")?,
            taps: None,
            capture: None,
            items: Vec::new(),
            written: iface.output("written", "messages written so far")?,
        })
    }

    fn window(&self, ports: &[recording::PortSpec]) -> Result<Option<Window>, HookError> {
        let text = self.trigger.get();
        if text.trim().is_empty() {
            return Ok(None);
        }
        let trigger: Trigger = text.parse().map_err(|e| HookError::new(format!("{e}")))?;
        let Some(index) = ports.iter().position(|p| p.name == trigger.port) else {
            return Err(HookError::new(format!(
                "trigger port {:?} is not among the ports recorded",
                trigger.port
            )));
        };
        let ns = |what: &str, ms: f64| {
            if !(ms.is_finite() && (0.0..=crate::checks::MAX_MS).contains(&ms)) {
                return Err(HookError::new(format!(
                    "{what} {}: expected 0 to {} ms (a day)",
                    crate::checks::number(ms),
                    crate::checks::MAX_MS
                )));
            }
            Ok((ms * 1e6) as u64)
        };
        let (pre, post) = (
            ns("pre_ms", self.pre_ms.get())?,
            ns("post_ms", self.post_ms.get())?,
        );
        Ok(Some(Window::new(
            trigger,
            index as u32,
            pre,
            post,
            recording::trigger::MAX_RING,
        )))
    }
}

impl Component for McapRecorder {
    fn configure_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        let selectors = self.ports.get();
        let activities = self.activities.get();
        if selectors.is_empty() && activities.is_empty() {
            return Err(HookError::new(
                "properties ports and activities are empty: name what to record",
            ));
        }
        let ports = resolve(&|n| ctx.peer(n).map_err(|e| e.to_string()), &selectors)
            .map_err(HookError::new)?;
        for a in &activities {
            ctx.peer(a)?;
        }
        self.window(&ports)?;
        let file = self.file.get();
        if file.is_empty() {
            return Err(HookError::new(
                "property file is empty: name the MCAP file to write",
            ));
        }
        crate::checks::new_file(Path::new(&file)).map_err(HookError::new)?;
        let buffer = self.buffer.get();
        if !(1..=super::taps::MAX_BUFFER).contains(&(buffer as usize)) {
            return Err(HookError::new(format!(
                "buffer {buffer}: expected 1 to {} samples a port may hold",
                super::taps::MAX_BUFFER
            )));
        }
        if !(1..=MAX_MB).contains(&self.max_mb.get()) {
            return Err(HookError::new(format!(
                "max_mb {}: expected 1 to {MAX_MB}",
                self.max_mb.get()
            )));
        }
        Ok(())
    }

    fn start_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        let ports = resolve(
            &|n| ctx.peer(n).map_err(|e| e.to_string()),
            &self.ports.get(),
        )
        .map_err(HookError::new)?;
        let window = self.window(&ports)?;
        let taps = Taps::open(
            &|n| ctx.peer(n).map_err(|e| e.to_string()),
            ports,
            &self.activities.get(),
            self.buffer.get() as usize,
        )
        .map_err(HookError::new)?;
        let mut notes = std::collections::BTreeMap::new();
        notes.insert("recorder".into(), ctx.name().to_string());
        notes.insert("trigger".into(), self.trigger.get());
        let options = Options {
            wall_offset_ns: wall_offset(),
            max_bytes: self.max_mb.get().saturating_mul(1 << 20),
            notes,
        };
        let file = self.file.get();
        let recorder = Recorder::create(
            Path::new(&file),
            taps.ports().to_vec(),
            taps.activities().to_vec(),
            options,
        )
        .map_err(|e| HookError::new(e.to_string()))?;
        self.capture = Some(Capture::new(recorder, window));
        self.taps = Some(taps);
        Ok(())
    }

    fn update_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        if let Err(e) = self.take() {
            // A full disk, an I/O error: the file (cut back to its last complete chunk) is
            // completed now, with what it holds and what it lost.
            self.finish(ctx.name());
            return Err(HookError::new(e.to_string()));
        }
        if self.capture.as_ref().is_some_and(Capture::done) {
            // The trigger's window is whole: the file is complete now, not at stop.
            self.finish(ctx.name());
        }
        Ok(())
    }

    fn stop_hook(&mut self, ctx: &mut Context<'_>) {
        if let Err(e) = self.take() {
            tracing::error!("recorder {}: {}: {e}", ctx.name(), self.file.get());
        }
        self.finish(ctx.name());
    }
}

impl McapRecorder {
    /// Writes what came since the last step.
    fn take(&mut self) -> Result<(), recording::RecordError> {
        let (Some(taps), Some(capture)) = (&mut self.taps, &mut self.capture) else {
            return Ok(());
        };
        // Taken before the drain, as the stream takes it: what was stamped before it came.
        let now = now_ns();
        self.items.clear();
        taps.drain(&mut self.items);
        capture.offer(std::mem::take(&mut self.items), now)?;
        self.written.write(&capture.written());
        Ok(())
    }

    /// Completes the file with what was lost, and lets go of the ports.
    fn finish(&mut self, name: &str) {
        let losses = self.taps.take().map(|t| t.losses()).unwrap_or_default();
        let Some(capture) = self.capture.take() else {
            return;
        };
        let file = self.file.get();
        match capture.finish(losses) {
            Ok(meta) => {
                let get = |k: &str| meta.get(k).map_or("?", String::as_str).to_string();
                match meta.get("error") {
                    Some(error) => tracing::error!(
                        "recorder {name}: {error}; {file} is complete: {} messages, {} lost",
                        get("messages"),
                        get("lost"),
                    ),
                    None => tracing::info!(
                        "recorder {name}: {file} finished: {} messages, {} lost",
                        get("messages"),
                        get("lost"),
                    ),
                }
            }
            Err(e) => tracing::error!("recorder {name}: {file}: {e}"),
        }
    }
}

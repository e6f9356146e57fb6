//! Marlin's SD-card commands, served by the board's file store
//! ([`Peripherals::files`]): printer hosts upload a job to the
//! "card", list it, print it from there and follow its progress.
//!
//! | command | effect | answer (then `ok`) |
//! |---|---|---|
//! | `M20` | list: the uploaded program (frame 03) as `program <stored>/<total> complete\|incomplete`, then each file | `Begin file list`, `<NAME> <size>` …, `End file list` |
//! | `M21` | mount the card ([`FileStore::mount`]) | `echo:SD card ok`, or `echo:SD init fail` (no card, a volume it cannot read) |
//! | `M22` | release the card (not while a file prints; [`FileStore::release`]): the file commands answer `echo:No media` until `M21` | `echo:SD card released` |
//! | `M23 <name>` | select a file: frame `Start`, `Pause`, `Stop`, `Rewind` and 52 act on it | `File opened: <name> Size: <size>`, `File selected` |
//! | `M24` | start the selected file, or resume it after `M25` or a pause | — |
//! | `M25` | pause: no more lines are read, the motion already queued finishes; other commands run meanwhile | — |
//! | `M26 S<byte>` | go on from byte `S` (not while printing) | — |
//! | `M27` | where the print is | `SD printing byte <byte>/<size>` or `Not SD printing` |
//! | `M27 S<s>` | the same report every `s` seconds (0: off) | — |
//! | `M28 <name>` | write the lines that follow to the file, up to `M29` (not while the machine moves) | `Writing to file: <name>` |
//! | `M29` | finish the file: it replaces one of the same name | `Done saving file.` |
//! | `M30 <name>` | delete a file (not the one printing, not while the machine moves) | `File deleted:<name>` |
//! | `M32 <name>` | select and start a file (Marlin's `M32 !<name>#` too) | as `M23` |
//!
//! When a file has run to its end `Done printing file` goes out. A name may start with `/` (the
//! card's root, as OctoPrint sends it); names follow
//! [`FileName`]'s rules, without regard to the case of letters.
//!
//! **Uploads.** From `M28` to `M29` every line received is stored and never run: its number and
//! checksum are checked as for any line, it is answered `ok`, and it is kept in its canonical
//! form (`docs/protocol.md` §2.4: the words as received, comments dropped, without its number
//! and checksum). What is not a line for the file acts as always and is not stored: the
//! realtime commands `M108`, `M112`, `M410` (the machine's, now), `M110` (the link's
//! numbering), `M999` (a reset), and a line the parser refuses (refused as always, as it would
//! be if it were streamed). A refused `M28` (bad name, no card, no room, the file printing)
//! answers `open failed, File: <name>.`, and the lines that follow up to `M29` are refused in
//! turn (`echo:E<code> …` then `ok`), so that a host that streams them anyway moves nothing. So
//! are the lines after one that could not be stored (the store full): the file is abandoned,
//! never kept in part. A host that leaves the link (a new session, another host) abandons its
//! upload.
//!
//! **Without a card** (a board without a file store) `M21` answers `echo:SD init fail` and the
//! other commands `echo:No media` (Marlin's answers), `M20` still lists the uploaded program.
//!
//! Failures are told in both forms: `echo:E<code> <name> <detail>` (§7.1) and, where Marlin has
//! one, its line (`open failed, File: <name>.`, `Deletion failed, File: <name>.`), then `ok`.

use embedded_io::Write;
use forja_hal_abstraction::files::{FileError, FileName, FileStore, MAX_NAME_LEN};
use forja_hal_abstraction::program::ProgramStore;
use forja_hal_abstraction::storage::RecordStorage;
use forja_motion::MachineState;
use forja_motion::effect::Storage;
use forja_motion::error::CommandError;
use forja_protocol::gcode::{Line, MAX_LINE_LEN};
use forja_protocol::reply::Reply;

use super::peripherals::{PeripheralError, Peripherals};
use super::text::{self, Refusal, Text};
use super::{Core, JobState, wire};
use crate::error::{FileRefusal, JobError};

/// Room for a name as a command gave it: a longest name, and one byte more to tell a longer
/// one.
const GIVEN_LEN: usize = MAX_NAME_LEN + 1;

/// A file name as a command gave it (a leading `/` taken off), kept for the answers; checked
/// when it is used.
#[derive(Clone, Copy)]
pub(super) struct Given {
    text: Text<GIVEN_LEN>,
}

impl Given {
    fn new(bytes: &[u8]) -> Self {
        let bytes = bytes.strip_prefix(b"/").unwrap_or(bytes);
        let mut text = Text::new();
        text.push(core::str::from_utf8(bytes).unwrap_or("?"));
        Self { text }
    }

    /// `M32`'s argument: Marlin's `!<name>#`, or the name alone.
    fn program(bytes: &[u8]) -> Self {
        match bytes.strip_prefix(b"!") {
            Some(rest) => {
                let end = rest.iter().position(|&b| b == b'#').unwrap_or(rest.len());
                Self::new(rest.get(..end).unwrap_or(rest))
            }
            None => Self::new(bytes),
        }
    }

    fn as_str(&self) -> &str {
        self.text.as_str()
    }

    /// The name, if it follows the rules.
    fn name(&self) -> Result<FileName, FileError> {
        FileName::new(self.text.as_bytes())
    }
}

/// A file command, with what it names copied out of its line.
#[derive(Clone, Copy)]
pub(super) enum FileCommand {
    /// `M20`.
    List,
    /// `M21`.
    Init,
    /// `M22`.
    Release,
    /// `M23`.
    Select(Given),
    /// `M24`.
    Start,
    /// `M25`.
    Pause,
    /// `M26 S<byte>`.
    SetPosition(u32),
    /// `M27`.
    Report,
    /// `M27 S<seconds>`.
    ReportEvery(u8),
    /// `M28`.
    BeginWrite(Given),
    /// `M29` outside an upload.
    EndWrite,
    /// `M30 <name>`.
    Delete(Given),
    /// `M32`.
    SelectAndStart(Given),
}

impl FileCommand {
    /// The command of a storage effect.
    pub(super) fn new(s: &Storage<'_>) -> Self {
        match *s {
            Storage::List => Self::List,
            Storage::Init => Self::Init,
            Storage::Release => Self::Release,
            Storage::Select(name) => Self::Select(Given::new(name)),
            Storage::Start => Self::Start,
            Storage::Pause => Self::Pause,
            Storage::SetPosition(byte) => Self::SetPosition(byte),
            Storage::Report => Self::Report,
            Storage::ReportEvery(seconds) => Self::ReportEvery(seconds),
            Storage::BeginWrite(name) => Self::BeginWrite(Given::new(name)),
            Storage::EndWrite(_) => Self::EndWrite,
            Storage::Delete(name) => Self::Delete(Given::new(name)),
            Storage::SelectAndStart(name) => Self::SelectAndStart(Given::program(name)),
        }
    }
}

/// Where the link's lines go.
#[derive(Clone, Copy)]
enum Upload {
    /// To the kernel.
    Off,
    /// Into this file, up to `M29`.
    Writing(FileName),
    /// Nowhere: each is refused with this, up to `M29` (the `M28` was refused, or a line
    /// could not be stored).
    Refusing(Refusal),
}

/// The card as the link's host sees it: mounted or released, the upload in progress, the
/// `M27 S` reports.
pub(super) struct Card {
    released: bool,
    upload: Upload,
    /// `M27 S` period, ms; 0 when off.
    report_ms: u32,
    next_report_ms: u32,
}

impl Card {
    /// Mounted, no upload, no reports.
    pub(super) const fn new() -> Self {
        Self {
            released: false,
            upload: Upload::Off,
            report_ms: 0,
            next_report_ms: 0,
        }
    }
}

/// The longest line of an answer here, its terminator not counted.
const SAY_LEN: usize = 160;

/// One line of text (as far as it fits) and its terminator, in one write.
fn say<W: Write>(out: &mut W, text: &str) {
    say_text(out, Text::<SAY_LEN>::new().push(text));
}

/// The line `line` and its terminator, in one write.
fn say_text<W: Write>(out: &mut W, line: &Text<SAY_LEN>) {
    let text = line.as_bytes();
    let mut bytes = [b'\n'; SAY_LEN + 1];
    if let Some(head) = bytes.get_mut(..text.len()) {
        head.copy_from_slice(text);
    }
    let _ = out.write_all(bytes.get(..=text.len()).unwrap_or(&[]));
}

/// `before`, the file's name as given, `after`: one line, as [`say`] writes it.
fn say_named<W: Write>(out: &mut W, before: &str, given: &Given, after: &str) {
    say_text(
        out,
        Text::new().push(before).push(given.as_str()).push(after),
    );
}

/// The refusal of a file command without a card: `E194 no-device sd-card`.
fn no_card() -> Refusal {
    Refusal::with(&PeripheralError::NoDevice, "sd-card")
}

/// The file's newlines before byte `end`, and whether the byte before `end` ends a line (or
/// `end` is 0). Reads the file through once.
fn newlines_before(
    files: &mut dyn FileStore,
    name: &FileName,
    end: u32,
) -> Result<(u32, bool), FileError> {
    let mut buf = [0u8; 256];
    let (mut at, mut count, mut last) = (0u32, 0u32, b'\n');
    while at < end {
        let want = buf.len().min((end - at) as usize);
        let n = files.read(name, at, buf.get_mut(..want).unwrap_or(&mut []))?;
        if n == 0 {
            break;
        }
        let chunk = buf.get(..n).unwrap_or(&[]);
        count += chunk.iter().filter(|&&b| b == b'\n').count() as u32;
        last = chunk.last().copied().unwrap_or(last);
        at += n as u32;
    }
    Ok((count, last == b'\n'))
}

impl<const N: usize, const B: usize, const Q: usize, P, X, S> Core<'_, N, B, Q, P, X, S>
where
    P: ProgramStore,
    X: Peripherals<N>,
    S: RecordStorage,
{
    /// The card's file store, unless the board has none or `M22` released it.
    fn card(&mut self) -> Option<&mut dyn FileStore> {
        if self.card.released {
            return None;
        }
        self.devices.parts.files()
    }

    /// `echo:E<code> …` for a command whose `ok` the caller sends.
    fn refused<W: Write>(&mut self, r: &Refusal, out: &mut W) {
        self.stats.refused = self.stats.refused.wrapping_add(1);
        wire::refused(out, r);
    }

    /// A file error, naming the file.
    fn file_refusal(e: FileError, given: &Given) -> Refusal {
        Refusal::with(&FileRefusal(e), given.as_str())
    }

    /// Whether the host asked for the card's status every period (`M27 S` above 0).
    pub(super) fn card_reporting(&self) -> bool {
        self.card.report_ms > 0
    }

    /// Carry out a file command from the link; its `ok` is the caller's.
    pub(super) fn file_command<W: Write>(&mut self, command: FileCommand, out: &mut W) {
        match command {
            FileCommand::List => self.list_files(out),
            FileCommand::Init => {
                self.card.released = false;
                let text = match self.card().map(|files| files.mount()) {
                    Some(Ok(())) => "SD card ok",
                    Some(Err(_)) | None => "SD init fail",
                };
                let _ = wire::reply(out, &Reply::Echo(text));
            }
            FileCommand::Report => self.report_status(out),
            FileCommand::ReportEvery(seconds) => {
                self.card.report_ms = u32::from(seconds) * 1000;
                self.card.next_report_ms = self.clock.ms.wrapping_add(self.card.report_ms);
            }
            FileCommand::EndWrite => {}
            // `M28` without a card is refused as any `M28`, so that its lines do not run.
            FileCommand::BeginWrite(given) => self.begin_write(&given, out),
            _ if self.card().is_none() => {
                let _ = wire::reply(out, &Reply::Echo("No media"));
            }
            FileCommand::Release => {
                if self.file_printing() {
                    return self.refused(&Refusal::new(&JobError::Busy), out);
                }
                let _ = self.job.select_program();
                if let Some(files) = self.card() {
                    files.release();
                }
                self.card.released = true;
                let _ = wire::reply(out, &Reply::Echo("SD card released"));
            }
            FileCommand::Select(given) => {
                let _ = self.select(&given, out);
            }
            FileCommand::SelectAndStart(given) => {
                if self.select(&given, out) {
                    self.start_file(out);
                }
            }
            FileCommand::Start => self.start_file(out),
            FileCommand::Pause => {
                // Nothing printing: nothing to pause (Marlin's answer too).
                let _ = self.job.suspend();
            }
            FileCommand::SetPosition(byte) => {
                if let Err(r) = self.set_position(byte) {
                    self.refused(&r, out);
                }
            }
            FileCommand::Delete(given) => {
                if let Err(r) = self.delete(&given) {
                    self.refused(&r, out);
                    say_named(out, "Deletion failed, File: ", &given, ".");
                } else {
                    say_named(out, "File deleted:", &given, "");
                }
            }
        }
    }

    /// The card is written (`M28`, `M30`) only while the machine is at rest, as the file
    /// store's contract asks: a flash erase holds the step interrupt off on some boards. An
    /// upload holds every line until `M29`, so nothing moves while it is open.
    fn at_rest_for_writes(&self) -> Result<(), Refusal> {
        if self.kernel.is_idle() {
            Ok(())
        } else {
            Err(Refusal::new(&CommandError::NotIdle))
        }
    }

    /// Whether the selected file runs or is paused: it may not be replaced, deleted or
    /// released.
    fn file_printing(&self) -> bool {
        self.job.file().is_some() && self.job_active()
    }

    /// `M20`: `Begin file list`, the uploaded program (`program <stored>/<total>
    /// complete|incomplete`, no line with no program), each file (`<NAME> <size>`),
    /// `End file list`; `echo:No media` after it without a card. The caller sends `ok`.
    pub(super) fn list_files<W: Write>(&mut self, out: &mut W) {
        let _ = out.write_all(b"Begin file list\n");
        if self.program.total() > 0 {
            let state = if self.program.is_complete() {
                "complete"
            } else {
                "incomplete"
            };
            let (len, total) = (self.program.len(), self.program.total());
            let mut line = Text::new();
            line.push("program ").push_number(len).push("/");
            line.push_number(total).push(" ").push(state);
            say_text(out, &line);
        }
        let mut failure = None;
        let card = self.card().is_some();
        if let Some(files) = self.card() {
            for index in 0.. {
                match files.file(index) {
                    Ok(Some(f)) => say_text(
                        out,
                        Text::new()
                            .push(f.name.as_str())
                            .push(" ")
                            .push_number(f.size),
                    ),
                    Ok(None) => break,
                    Err(e) => {
                        failure = Some(e);
                        break;
                    }
                }
            }
        }
        let _ = out.write_all(b"End file list\n");
        if !card {
            let _ = wire::reply(out, &Reply::Echo("No media"));
        }
        if let Some(e) = failure {
            self.refused(&Refusal::new(&FileRefusal(e)), out);
        }
    }

    /// `M27`'s answer: `SD printing byte <byte>/<size>` while the selected file is being
    /// printed, else `Not SD printing`.
    fn report_status<W: Write>(&mut self, out: &mut W) {
        match self.job.file() {
            Some(f) if f.printing => say_text(
                out,
                Text::new()
                    .push("SD printing byte ")
                    .push_number(f.byte)
                    .push("/")
                    .push_number(f.size),
            ),
            _ => say(out, "Not SD printing"),
        }
    }

    /// `M23` (and the first half of `M32`): select the file, answering `File opened: <name>
    /// Size: <size>` and `File selected`, or the refusal and `open failed, File: <name>.`.
    /// Whether it was selected.
    fn select<W: Write>(&mut self, given: &Given, out: &mut W) -> bool {
        let selected = self.try_select(given);
        match selected {
            Ok(size) => {
                say_text(
                    out,
                    Text::new()
                        .push("File opened: ")
                        .push(given.as_str())
                        .push(" Size: ")
                        .push_number(size),
                );
                say(out, "File selected");
            }
            Err(r) => {
                self.refused(&r, out);
                say_named(out, "open failed, File: ", given, ".");
            }
        }
        selected.is_ok()
    }

    /// Select the file `given`: its size, once its lines are counted.
    fn try_select(&mut self, given: &Given) -> Result<u32, Refusal> {
        let name = given.name().map_err(|e| Self::file_refusal(e, given))?;
        if self.job_active() {
            return Err(Refusal::new(&JobError::Busy));
        }
        let files = self.card().ok_or_else(no_card)?;
        let counted = files
            .size(&name)
            .and_then(|size| Ok((size, newlines_before(files, &name, size)?)));
        let (size, (newlines, ends_a_line)) = counted.map_err(|e| Self::file_refusal(e, given))?;
        let lines = newlines + u32::from(!ends_a_line);
        self.job
            .select_file(name, size, lines)
            .map_err(|e| Refusal::new(&e))?;
        Ok(size)
    }

    /// `M24` (and the second half of `M32`): start the selected file, or resume it.
    fn start_file<W: Write>(&mut self, out: &mut W) {
        let refusal = match self.kernel.state() {
            _ if self.job.file().is_none() => Some(Refusal::new(&JobError::NoFileSelected)),
            MachineState::Alarm(_) => Some(Refusal::new(&CommandError::Locked)),
            MachineState::Halted => Some(Refusal::new(&CommandError::Halted)),
            _ => None,
        };
        let started = match refusal {
            Some(r) => Err(r),
            None => self
                .job
                .start(&mut self.kernel, &mut self.program, self.now)
                .map_err(|e| text::job_refusal(&e)),
        };
        match started {
            Ok(()) => self.taken = true,
            Err(r) => self.refused(&r, out),
        }
    }

    /// `M26 S<byte>`: go on from `byte` (its line counted from the start of the file).
    fn set_position(&mut self, byte: u32) -> Result<(), Refusal> {
        let Some(file) = self.job.file() else {
            return Err(Refusal::new(&JobError::NoFileSelected));
        };
        if self.job_active() {
            return Err(Refusal::new(&JobError::Busy));
        }
        let byte = byte.min(file.size);
        let files = self.card().ok_or_else(no_card)?;
        let (newlines, _) = newlines_before(files, &file.name, byte)
            .map_err(|e| Refusal::with(&FileRefusal(e), file.name.as_str()))?;
        self.job
            .set_file_position(byte, newlines + 1)
            .map_err(|e| Refusal::new(&e))
    }

    /// `M30 <name>`: delete the file (deselected if it was selected).
    fn delete(&mut self, given: &Given) -> Result<(), Refusal> {
        let name = given.name().map_err(|e| Self::file_refusal(e, given))?;
        let selected = self.job.file().is_some_and(|f| f.name == name);
        if selected && self.job_active() {
            return Err(Refusal::new(&JobError::Busy));
        }
        self.at_rest_for_writes()?;
        let files = self.card().ok_or_else(no_card)?;
        files
            .remove(&name)
            .map_err(|e| Self::file_refusal(e, given))?;
        if selected {
            let _ = self.job.select_program();
        }
        Ok(())
    }

    /// `M28 <name>`: the lines up to `M29` go to the file; `Writing to file: <name>`, or the
    /// refusal and `open failed, File: <name>.` (and the lines up to `M29` are refused).
    fn begin_write<W: Write>(&mut self, given: &Given, out: &mut W) {
        let opened = self.try_begin_write(given);
        match opened {
            Ok(name) => {
                self.card.upload = Upload::Writing(name);
                say_named(out, "Writing to file: ", given, "");
            }
            Err(r) => {
                self.card.upload = Upload::Refusing(r);
                self.refused(&r, out);
                say_named(out, "open failed, File: ", given, ".");
            }
        }
    }

    fn try_begin_write(&mut self, given: &Given) -> Result<FileName, Refusal> {
        let name = given.name().map_err(|e| Self::file_refusal(e, given))?;
        if self.file_printing() && self.job.file().is_some_and(|f| f.name == name) {
            return Err(Refusal::new(&JobError::Busy));
        }
        self.at_rest_for_writes()?;
        let files = self.card().ok_or_else(no_card)?;
        // A write left by a host that went is dropped (there is one link's upload at a time).
        let _ = files.abandon();
        files
            .create(&name)
            .map_err(|e| Self::file_refusal(e, given))?;
        Ok(name)
    }

    /// A line of the link while an upload is open (`M28` to `M29`): stored, or refused, and
    /// answered here (`true`); `false` for what acts as always (`M112`, `M410`) or when no
    /// upload is open.
    pub(super) fn upload_line<W: Write>(&mut self, line: &Line<'_>, out: &mut W) -> bool {
        let upload = self.card.upload;
        if matches!(upload, Upload::Off) || line.is_command(b'M', 112) || line.is_command(b'M', 410)
        {
            return false;
        }
        if line.is_command(b'M', 29) {
            self.card.upload = Upload::Off;
            if let Upload::Writing(name) = upload {
                match self.finish_write(&name) {
                    Ok(()) => say(out, "Done saving file."),
                    Err(r) => self.refused(&r, out),
                }
            }
            self.ok(out);
            return true;
        }
        let stored = match upload {
            // A comment or a blank line: nothing to store, nothing to refuse.
            _ if line.is_empty() => Ok(()),
            Upload::Writing(name) => self.store_line(line, &name),
            Upload::Refusing(r) => Err(r),
            Upload::Off => Ok(()),
        };
        match stored {
            Ok(()) => self.ok(out),
            Err(r) => {
                // A file is never kept in part: one line that cannot be stored ends it.
                if let (Upload::Writing(_), Some(files)) = (upload, self.devices.parts.files()) {
                    let _ = files.abandon();
                }
                self.card.upload = Upload::Refusing(r);
                self.refuse(&r, out);
            }
        }
        true
    }

    /// Append `line` to the file being written, in its canonical form, without its number
    /// and checksum.
    fn store_line(&mut self, line: &Line<'_>, name: &FileName) -> Result<(), Refusal> {
        // First: a board without a store has nothing more to do here.
        let files = self.devices.parts.files().ok_or_else(no_card)?;
        let mut buf = [0u8; MAX_LINE_LEN + 16];
        let len = line
            .encode(&mut buf)
            .map_err(|e| Refusal::with(&e, name.as_str()))?;
        let encoded = buf.get(..len).unwrap_or(&[]);
        // `N<n> <words>*<check>`: the words alone.
        let body = match line.number() {
            Some(_) => {
                let start = encoded
                    .iter()
                    .position(|&b| b == b' ')
                    .map_or(len, |i| i + 1);
                let end = encoded.iter().rposition(|&b| b == b'*').unwrap_or(len);
                encoded.get(start..end.max(start)).unwrap_or(&[])
            }
            None => encoded,
        };
        let mut stored = [0u8; MAX_LINE_LEN + 16];
        let with_end = stored.get_mut(..body.len() + 1).unwrap_or(&mut []);
        if let Some((end, text)) = with_end.split_last_mut() {
            text.copy_from_slice(body);
            *end = b'\n';
        }
        files
            .append(with_end)
            .map_err(|e| Refusal::with(&FileRefusal(e), name.as_str()))
    }

    /// `M29`: finish the file; a selected file of the same name is deselected (it changed).
    /// A file of the name of the one printing is abandoned instead.
    fn finish_write(&mut self, name: &FileName) -> Result<(), Refusal> {
        let printing = self.file_printing() && self.job.file().is_some_and(|f| f.name == *name);
        let files = self.devices.parts.files().ok_or_else(no_card)?;
        if printing {
            let _ = files.abandon();
            return Err(Refusal::with(&JobError::Busy, name.as_str()));
        }
        let finished = files.finish();
        if finished.is_err() {
            let _ = files.abandon();
        }
        finished.map_err(|e| Refusal::with(&FileRefusal(e), name.as_str()))?;
        if self.job.file().is_some_and(|f| f.name == *name) {
            let _ = self.job.select_program();
        }
        Ok(())
    }

    /// The host left the link: its upload, if any, is abandoned.
    pub(super) fn end_upload(&mut self) {
        if let Upload::Writing(_) = self.card.upload
            && let Some(files) = self.devices.parts.files()
        {
            let _ = files.abandon();
        }
        self.card.upload = Upload::Off;
    }

    /// At each poll: read the running file ahead of the line being fed (a file that cannot
    /// be read stops the job, with a 56), `Done printing file` once it has finished, and the
    /// `M27 S` reports that are due.
    pub(super) fn serve_files<W: Write>(&mut self, out: &mut W) {
        if self.job.state() == JobState::Running
            && let Some(file) = self.job.file()
        {
            let read = match self.devices.parts.files() {
                Some(files) => self.job.read_ahead(files),
                None => Err(FileError::Device),
            };
            if let Err(e) = read {
                self.job.stop(&mut self.kernel);
                let r = Refusal::with(&FileRefusal(e), file.name.as_str());
                self.error_frame(&r, out);
            }
        }
        if self.job.take_file_done() {
            say(out, "Done printing file");
        }
        if self.card.report_ms > 0 && self.clock.reached(self.card.next_report_ms) {
            self.card.next_report_ms = self.clock.ms.wrapping_add(self.card.report_ms);
            self.report_status(out);
        }
    }
}

//! File dialogs that always work. The desktop's own dialog (rfd over the XDG desktop
//! portal) runs on its own thread when a portal is there; without one (no session
//! bus, no portal process, or a dialog that comes back empty at once, which is how a
//! missing portal answers) the window draws its own dialog in egui. Either way the
//! UI thread never blocks on a dialog.

use eframe::egui;
use std::path::{Path, PathBuf};
use std::sync::mpsc::{Receiver, TryRecvError};
use std::time::{Duration, Instant};

/// What a dialog asks for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    Open,
    Save,
    Folder,
}

/// A dialog to show: its kind, title, file filter and suggested name.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Request {
    pub kind: Kind,
    pub title: String,
    /// Name of the filter and the extensions it lets through (lower case, no dot);
    /// empty: every file.
    pub filter: (String, Vec<String>),
    /// The file name a save dialog starts with.
    pub file_name: String,
}

impl Request {
    pub fn new(kind: Kind, title: &str, filter: &str, extensions: &[&str], file_name: &str) -> Self {
        Request {
            kind,
            title: title.into(),
            filter: (filter.into(), extensions.iter().map(|e| e.to_string()).collect()),
            file_name: file_name.into(),
        }
    }

    fn accepts(&self, name: &str) -> bool {
        let ext = Path::new(name).extension().map(|e| e.to_string_lossy().to_lowercase());
        self.filter.1.is_empty() || ext.is_some_and(|e| self.filter.1.contains(&e))
    }

    /// A save path with the filter's extension added when the typed name has none.
    fn with_extension(&self, path: PathBuf) -> PathBuf {
        match (&self.filter.1.first(), path.extension()) {
            (Some(ext), None) if self.kind == Kind::Save => path.with_extension(ext),
            _ => path,
        }
    }
}

/// What a dialog ended in.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Outcome {
    Pending,
    Cancelled,
    Picked(PathBuf),
}

/// Whether the XDG desktop portal can answer a dialog: a session bus and a running
/// `xdg-desktop-portal` process (Linux). Elsewhere rfd uses the system's own dialogs.
pub fn portal_available() -> bool {
    if !cfg!(target_os = "linux") {
        return true;
    }
    if std::env::var_os("DBUS_SESSION_BUS_ADDRESS").is_none() {
        return false;
    }
    let Ok(procs) = std::fs::read_dir("/proc") else { return false };
    procs.flatten().any(|p| {
        std::fs::read_to_string(p.path().join("comm")).is_ok_and(|c| c.trim().starts_with("xdg-desktop-portal"))
    })
}

/// An answer faster than this from the portal is not a person cancelling: it is a
/// portal that could not show the dialog.
const NO_DIALOG_WITHIN: Duration = Duration::from_millis(250);

/// The dialog in flight: the desktop's, on its thread, or the window's own.
pub enum Dialog {
    /// The desktop's dialog on its thread; the answer comes with how long the
    /// dialog took, timed on that thread (not when the UI polls).
    Native {
        request: Request,
        answer: Receiver<(Option<PathBuf>, Duration)>,
    },
    Drawn(DrawnDialog),
}

impl Dialog {
    /// Opens `request`: the desktop's dialog when `native` (and a thread can be had),
    /// else the window's own, starting in `dir`.
    pub fn open(request: Request, native: bool, dir: &Path) -> Dialog {
        if native {
            let (tx, rx) = std::sync::mpsc::channel();
            let r = request.clone();
            let spawned = std::thread::Builder::new().name("nimbus-file-dialog".into()).spawn(move || {
                let asked = Instant::now();
                let mut d = rfd::FileDialog::new().set_title(&r.title);
                if !r.filter.1.is_empty() {
                    d = d.add_filter(&r.filter.0, &r.filter.1);
                }
                let picked = match r.kind {
                    Kind::Open => d.pick_file(),
                    Kind::Save => d.set_file_name(&r.file_name).save_file(),
                    Kind::Folder => d.pick_folder(),
                };
                let _ = tx.send((picked, asked.elapsed()));
            });
            if spawned.is_ok() {
                return Dialog::Native { request, answer: rx };
            }
        }
        Dialog::Drawn(DrawnDialog::new(request, dir))
    }

    /// Shows the window's dialog or polls the desktop's. A desktop dialog that
    /// answers nothing at once turns into the window's own (and `native_works` is
    /// cleared, so the next dialog goes there directly).
    pub fn show(&mut self, ctx: &egui::Context, native_works: &mut bool, dir: &Path) -> Outcome {
        match self {
            Dialog::Native { request, answer } => match answer.try_recv() {
                Ok((Some(path), _)) => Outcome::Picked(request.with_extension(path)),
                // Nothing at once, or the thread gone: the portal could not show it.
                Ok((None, took)) if took < NO_DIALOG_WITHIN => {
                    *native_works = false;
                    *self = Dialog::Drawn(DrawnDialog::new(request.clone(), dir));
                    Outcome::Pending
                }
                Err(TryRecvError::Disconnected) => {
                    *native_works = false;
                    *self = Dialog::Drawn(DrawnDialog::new(request.clone(), dir));
                    Outcome::Pending
                }
                Ok((None, _)) => Outcome::Cancelled,
                Err(TryRecvError::Empty) => {
                    ctx.request_repaint_after(Duration::from_millis(50));
                    Outcome::Pending
                }
            },
            Dialog::Drawn(d) => d.show(ctx),
        }
    }
}

/// A file dialog drawn in egui: the folder as an editable path, its sub-folders and
/// the files the filter lets through, a file name for saving.
pub struct DrawnDialog {
    request: Request,
    dir: PathBuf,
    /// The folder field as typed.
    dir_text: String,
    name: String,
    entries: Vec<(String, bool)>,
    /// Why the folder cannot be listed, or why the choice is refused.
    problem: Option<String>,
}

impl DrawnDialog {
    pub fn new(request: Request, dir: &Path) -> Self {
        let name = if request.kind == Kind::Save { request.file_name.clone() } else { String::new() };
        let mut d = DrawnDialog {
            request,
            dir: PathBuf::new(),
            dir_text: String::new(),
            name,
            entries: Vec::new(),
            problem: None,
        };
        d.enter(dir.to_path_buf());
        d
    }

    /// The folder shown.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    fn enter(&mut self, dir: PathBuf) {
        let dir = std::path::absolute(&dir).unwrap_or(dir);
        match std::fs::read_dir(&dir) {
            Ok(rd) => {
                let mut entries: Vec<(String, bool)> = rd
                    .flatten()
                    .filter_map(|e| {
                        let name = e.file_name().to_string_lossy().into_owned();
                        let is_dir = e.path().is_dir();
                        (!name.starts_with('.') && (is_dir || self.request.accepts(&name))).then_some((name, is_dir))
                    })
                    .collect();
                entries.sort_by(|a, b| b.1.cmp(&a.1).then_with(|| a.0.to_lowercase().cmp(&b.0.to_lowercase())));
                self.entries = entries;
                self.dir_text = dir.display().to_string();
                self.dir = dir;
                self.problem = None;
            }
            Err(e) => {
                self.problem = Some(format!("cannot list {}: {e}", dir.display()));
                self.dir_text = self.dir.display().to_string();
            }
        }
    }

    /// The path the dialog would answer now, or why it cannot.
    fn choice(&self) -> Result<PathBuf, String> {
        match self.request.kind {
            Kind::Folder => Ok(self.dir.clone()),
            Kind::Open | Kind::Save if self.name.trim().is_empty() => Err("choose or type a file name".into()),
            Kind::Open => {
                let p = self.dir.join(self.name.trim());
                if p.is_file() { Ok(p) } else { Err(format!("{} is not a file", p.display())) }
            }
            Kind::Save => {
                let p = self.request.with_extension(self.dir.join(self.name.trim()));
                if p.is_dir() { Err(format!("{} is a folder", p.display())) } else { Ok(p) }
            }
        }
    }

    pub fn show(&mut self, ctx: &egui::Context) -> Outcome {
        let mut outcome = Outcome::Pending;
        let verb = match self.request.kind {
            Kind::Open => "Open",
            Kind::Save => "Save",
            Kind::Folder => "Choose this folder",
        };
        let modal = egui::Modal::new(egui::Id::unique("nimbus-file-dialog")).show(ctx, |ui| {
            ui.set_width(520.0);
            ui.heading(&self.request.title);
            ui.horizontal(|ui| {
                if ui.button("up").on_hover_text("the parent folder").clicked() {
                    if let Some(parent) = self.dir.parent().map(Path::to_path_buf) {
                        self.enter(parent);
                    }
                }
                let label = ui.label("folder");
                let r =
                    ui.add(egui::TextEdit::singleline(&mut self.dir_text).desired_width(400.0)).labelled_by(label.id);
                if r.lost_focus() && ui.input(|i| i.key_pressed(egui::Key::Enter)) {
                    self.enter(PathBuf::from(self.dir_text.clone()));
                }
            });
            egui::ScrollArea::vertical().max_height(280.0).auto_shrink([false, false]).show(ui, |ui| {
                let mut go = None;
                for (name, is_dir) in &self.entries {
                    let text = if *is_dir { format!("{name}/") } else { name.clone() };
                    let selected = !*is_dir && *name == self.name;
                    let r = ui.selectable_label(selected, text);
                    if r.clicked() {
                        if *is_dir {
                            go = Some(self.dir.join(name));
                        } else {
                            self.name = name.clone();
                        }
                    }
                    // A double-click opens; when saving it only fills in the name, so
                    // replacing a file always goes through the notice below.
                    if r.double_clicked() && !*is_dir && self.request.kind == Kind::Open {
                        self.name = name.clone();
                        if let Ok(p) = self.choice() {
                            outcome = Outcome::Picked(p);
                        }
                    }
                }
                if self.entries.is_empty() {
                    ui.weak("(nothing here the filter lets through)");
                }
                if let Some(dir) = go {
                    self.enter(dir);
                }
            });
            if self.request.kind != Kind::Folder {
                ui.horizontal(|ui| {
                    let label = ui.label("file name");
                    ui.add(egui::TextEdit::singleline(&mut self.name).desired_width(360.0)).labelled_by(label.id);
                    if !self.request.filter.1.is_empty() {
                        ui.weak(format!("{} (.{})", self.request.filter.0, self.request.filter.1.join(", .")));
                    }
                });
            }
            if self.request.kind == Kind::Save {
                if let Ok(p) = self.choice() {
                    if p.exists() {
                        ui.label(format!("{} exists and will be replaced", p.display()));
                    }
                }
            }
            if let Some(problem) = &self.problem {
                ui.colored_label(egui::Color32::from_rgb(255, 110, 90), problem);
            }
            ui.separator();
            ui.horizontal(|ui| {
                if ui.button(verb).clicked() {
                    match self.choice() {
                        Ok(p) => outcome = Outcome::Picked(p),
                        Err(e) => self.problem = Some(e),
                    }
                }
                if ui.button("Cancel").clicked() {
                    outcome = Outcome::Cancelled;
                }
            });
        });
        if modal.should_close() && outcome == Outcome::Pending {
            outcome = Outcome::Cancelled;
        }
        outcome
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A portal that answers "nothing" at once is a portal that could not show the
    /// dialog: the window's own takes over, and later dialogs go there directly. A
    /// late empty answer is a person cancelling.
    #[test]
    fn an_empty_answer_at_once_falls_back_to_the_drawn_dialog() {
        let ctx = egui::Context::default();
        let req = Request::new(Kind::Open, "Open", "Nimbus scene", &["toml"], "");
        let (tx, rx) = std::sync::mpsc::channel();
        tx.send((None, Duration::from_millis(3))).unwrap();
        let mut d = Dialog::Native { request: req.clone(), answer: rx };
        let mut native = true;
        // However late the UI looks: the answer's own timing decides.
        std::thread::sleep(2 * NO_DIALOG_WITHIN);
        assert_eq!(d.show(&ctx, &mut native, Path::new(".")), Outcome::Pending);
        assert!(matches!(d, Dialog::Drawn(_)) && !native);
        let (tx, rx) = std::sync::mpsc::channel();
        tx.send((None, 2 * NO_DIALOG_WITHIN)).unwrap();
        let mut d = Dialog::Native { request: req.clone(), answer: rx };
        let mut native = true;
        assert_eq!(d.show(&ctx, &mut native, Path::new(".")), Outcome::Cancelled);
        assert!(native);
        let (tx, rx) = std::sync::mpsc::channel();
        tx.send((Some(PathBuf::from("/x/s.toml")), Duration::from_secs(3))).unwrap();
        let mut d = Dialog::Native { request: req, answer: rx };
        assert_eq!(d.show(&ctx, &mut native, Path::new(".")), Outcome::Picked(PathBuf::from("/x/s.toml")));
    }

    #[test]
    fn the_drawn_dialog_lists_folders_and_filtered_files_and_adds_the_extension() {
        let tmp = tempfile::tempdir().unwrap();
        std::fs::create_dir(tmp.path().join("sub")).unwrap();
        std::fs::create_dir(tmp.path().join("d.toml")).unwrap();
        std::fs::write(tmp.path().join("b.toml"), "").unwrap();
        std::fs::write(tmp.path().join("A.TOML"), "").unwrap();
        std::fs::write(tmp.path().join("c.png"), "").unwrap();
        std::fs::write(tmp.path().join(".hidden.toml"), "").unwrap();
        let req = Request::new(Kind::Save, "Save scene", "Nimbus scene", &["toml"], "scene");
        let mut d = DrawnDialog::new(req, tmp.path());
        let names: Vec<&str> = d.entries.iter().map(|(n, _)| n.as_str()).collect();
        assert_eq!(names, ["d.toml", "sub", "A.TOML", "b.toml"]);
        assert_eq!(d.choice().unwrap(), std::path::absolute(tmp.path()).unwrap().join("scene.toml"));
        d.name = "d".into();
        assert!(d.choice().unwrap_err().contains("is a folder"), "d + .toml is a folder");
        d.enter(tmp.path().join("missing"));
        assert!(d.problem.as_deref().unwrap().contains("cannot list"));
        assert_eq!(d.dir(), std::path::absolute(tmp.path()).unwrap(), "a folder that cannot be listed is not entered");
        let open = Request::new(Kind::Open, "Open", "Nimbus scene", &["toml"], "");
        let mut d = DrawnDialog::new(open, tmp.path());
        d.name = "nothing.toml".into();
        assert!(d.choice().unwrap_err().contains("is not a file"));
        d.name = "b.toml".into();
        assert!(d.choice().is_ok());
    }
}

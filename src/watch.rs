//! `pbrl watch`: a run's learnt policy, or two side by side on the same episode seeds,
//! drawn by the labelling page's own drawing: one self-contained HTML file (the page in
//! its watch mode, the episodes inside it) and an animated GIF of the same frames, which
//! headless Chromium draws from that file.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use anyhow::{bail, Context, Result};
use pbrl_actor::evaluate::{episode_with, Acting};
use pbrl_actor::policy::Policy;
use pbrl_actor::replay::{readout, scene, watch as replay};
use pbrl_actor::{FeedingWorld, WorldConfig};

use crate::eval::{open_runs, same_world, seeds, OnArgs, Person, Run};

#[derive(clap::Args, Debug)]
pub struct WatchArgs {
    /// One run folder (its episodes two at a time) or two (side by side on the same
    /// episode seeds, the first on the left).
    #[arg(required = true, num_args = 1..=2)]
    pub runs: Vec<PathBuf>,
    #[command(flatten)]
    pub on: OnArgs,
    /// Episodes shown (of each run, with two runs; pairs of them, with one).
    #[arg(long, default_value_t = 2)]
    pub episodes: u32,
    /// Act with sampled actions instead of the mean.
    #[arg(long)]
    pub sampled: bool,
    /// The HTML file (default: watch.html in the first run's folder).
    #[arg(long, value_name = "FILE")]
    pub html: Option<PathBuf>,
    /// The animated GIF (default: the HTML file's name with .gif).
    #[arg(long, value_name = "FILE")]
    pub gif: Option<PathBuf>,
    /// Write the HTML file only (no GIF, no Chromium needed).
    #[arg(long)]
    pub no_gif: bool,
    /// The GIF shows every STEP-th world step (1: real time at 10 frames a second).
    #[arg(long, default_value_t = 1)]
    pub step: u32,
    /// The GIF's width in pixels.
    #[arg(long, default_value_t = 960)]
    pub width: u32,
}

/// One episode of `run`'s policy drawn as the page draws an attempt.
fn drawn(run: &Run, world: &WorldConfig, seed: u64, acting: Acting) -> Result<serde_json::Value> {
    let policy = Policy::from_weights(&run.policy.weights)?;
    let mut w = FeedingWorld::new(world.clone()).context("building the feeding world")?;
    let t = episode_with(&policy, &mut w, seed, acting)?;
    let (t, food) = replay(world, seed, &t.actions)?;
    let mut s = scene(&t, world)?;
    s.readout = readout(&t, &food)?;
    Ok(serde_json::to_value(&s)?)
}

/// The labelling page, whose watch mode plays embedded episodes, as one file (its style
/// sheet and scripts inline) with `data` inside it.
pub fn page_with(data: &serde_json::Value) -> Result<String> {
    // NOTE: "</" inside a script element would end it; "<\/" is the same JSON string.
    let json = serde_json::to_string(data)?.replace("</", "<\\/");
    pbrl_teacher::web::page_inline(&format!(
        "<script id=\"pbrl-watch\" type=\"application/json\">{json}</script>\n"
    ))
}

/// The episodes to show: one pair per shown episode.
fn pairs(args: &WatchArgs, runs: &[Run], world: &[WorldConfig]) -> Result<Vec<serde_json::Value>> {
    let acting = if args.sampled {
        Acting::Sampled
    } else {
        Acting::Mean
    };
    let n = args.episodes as usize;
    let all = seeds(if runs.len() == 1 {
        2 * args.episodes
    } else {
        args.episodes
    });
    (0..n)
        .map(|k| {
            let (left, right, display) = if runs.len() == 1 {
                let (a, b) = (all[2 * k], all[2 * k + 1]);
                (
                    drawn(&runs[0], &world[0], a, acting)?,
                    drawn(&runs[0], &world[0], b, acting)?,
                    format!("episodes {} and {} of {}", 2 * k + 1, 2 * k + 2, 2 * n),
                )
            } else {
                let s = all[k];
                (
                    drawn(&runs[0], &world[0], s, acting)?,
                    drawn(&runs[1], &world[1], s, acting)?,
                    format!("episode {} of {n}, the same seed on both sides", k + 1),
                )
            };
            Ok(serde_json::json!({ "query": k, "display": display, "left": left, "right": right }))
        })
        .collect()
}

/// A headless Chromium, if there is one (`PBRL_CHROMIUM` first).
fn chromium() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("PBRL_CHROMIUM") {
        return Some(PathBuf::from(p));
    }
    let path = std::env::var_os("PATH")?;
    for dir in std::env::split_paths(&path) {
        for name in ["chromium", "chromium-browser", "google-chrome", "chrome"] {
            let p = dir.join(name);
            if p.is_file() {
                return Some(p);
            }
        }
    }
    None
}

/// The frames the page draws in capture mode: width, height, delay and RGBA pixels.
struct Frames {
    width: u32,
    height: u32,
    delay_ms: u32,
    rgba: Vec<Vec<u8>>,
}

/// Have headless Chromium open `html` (a page in capture mode) and read back its frames.
fn capture(browser: &Path, html: &Path) -> Result<Frames> {
    let profile = html
        .parent()
        .unwrap_or(Path::new("."))
        .join("chromium-profile");
    let url = format!(
        "file://{}",
        html.canonicalize()
            .with_context(|| format!("finding {}", html.display()))?
            .display()
    );
    let out = Command::new(browser)
        .args([
            "--headless=new",
            "--no-sandbox",
            "--disable-gpu",
            "--hide-scrollbars",
            "--force-device-scale-factor=1",
            "--window-size=1280,900",
            "--virtual-time-budget=600000",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .args(["--dump-dom", &url])
        .stdin(Stdio::null())
        .output()
        .with_context(|| format!("running {}", browser.display()))?;
    let _ = std::fs::remove_dir_all(&profile);
    let dom = String::from_utf8_lossy(&out.stdout);
    let Some(start) = dom.rfind("<pre id=\"pbrl-frames\"") else {
        bail!(
            "{} drew no frames (exit {}): {}",
            browser.display(),
            out.status,
            String::from_utf8_lossy(&out.stderr)
                .lines()
                .rev()
                .take(5)
                .collect::<Vec<_>>()
                .join(" | ")
        );
    };
    let body = &dom[start..];
    let open = body.find('>').context("the frames element is cut")? + 1;
    let close = body.find("</pre>").context("the frames element is cut")?;
    // NOTE: the text is JSON of data URLs (base64) and numbers: nothing the DOM escapes
    // but quotes, which it leaves as they are in text.
    let text = body[open..close]
        .replace("&quot;", "\"")
        .replace("&amp;", "&");
    #[derive(serde::Deserialize)]
    struct Dump {
        width: u32,
        height: u32,
        delay_ms: u32,
        frames: Vec<String>,
    }
    let dump: Dump = serde_json::from_str(&text).context("reading the page's frames")?;
    let rgba = dump
        .frames
        .iter()
        .enumerate()
        .map(|(k, url)| {
            let b64 = url
                .strip_prefix("data:image/png;base64,")
                .with_context(|| format!("frame {k} is not a PNG data URL"))?;
            let bytes = base64::Engine::decode(&base64::engine::general_purpose::STANDARD, b64)
                .with_context(|| format!("frame {k}: base64"))?;
            decode_png(&bytes, dump.width, dump.height).with_context(|| format!("frame {k}"))
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(Frames {
        width: dump.width,
        height: dump.height,
        delay_ms: dump.delay_ms,
        rgba,
    })
}

fn tempfile_dir() -> Result<PathBuf> {
    let dir = std::env::temp_dir().join(format!("pbrl-watch-{}", std::process::id()));
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    Ok(dir)
}

/// An RGBA picture of `width` x `height` from PNG bytes.
fn decode_png(bytes: &[u8], width: u32, height: u32) -> Result<Vec<u8>> {
    let mut dec = png::Decoder::new(std::io::Cursor::new(bytes));
    dec.set_transformations(png::Transformations::EXPAND | png::Transformations::ALPHA);
    let mut reader = dec.read_info()?;
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf)?;
    if (info.width, info.height) != (width, height) {
        bail!(
            "{}x{} where the page said {width}x{height}",
            info.width,
            info.height
        );
    }
    buf.truncate(info.buffer_size());
    Ok(match info.color_type {
        png::ColorType::Rgba => buf,
        png::ColorType::GrayscaleAlpha => buf
            .chunks(2)
            .flat_map(|p| [p[0], p[0], p[0], p[1]])
            .collect(),
        c => bail!("colour type {c:?}"),
    })
}

/// Write `frames` as a looping GIF: each frame after the first keeps only the pixels that
/// changed (the rest transparent over the frame before), which keeps the file small.
fn write_gif(frames: &Frames, path: &Path) -> Result<()> {
    let (w, h) = (frames.width as u16, frames.height as u16);
    let file =
        std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let mut enc = gif::Encoder::new(std::io::BufWriter::new(file), w, h, &[])?;
    enc.set_repeat(gif::Repeat::Infinite)?;
    let mut prev: Option<&Vec<u8>> = None;
    for rgba in &frames.rgba {
        let mut px = rgba.clone();
        if let Some(p) = prev {
            for (a, b) in px.chunks_mut(4).zip(p.chunks(4)) {
                if a == b {
                    a[3] = 0;
                }
            }
        }
        // NOTE: the first frame is opaque (the page's white), so alpha 0 only marks
        // unchanged pixels.
        let mut f = gif::Frame::from_rgba_speed(w, h, &mut px, 10);
        f.delay = (frames.delay_ms / 10).max(1) as u16;
        f.dispose = gif::DisposalMethod::Keep;
        enc.write_frame(&f)?;
        prev = Some(rgba);
    }
    enc.into_inner()?
        .flush()
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

pub fn watch(args: WatchArgs) -> Result<()> {
    if args.episodes == 0 {
        bail!("--episodes: 0; show at least one");
    }
    if args.step == 0 {
        bail!("--step: 0; at least 1");
    }
    let runs = open_runs(&args.runs, args.on.checkpoint)?;
    same_world(&runs, args.on.other_world)?;
    let person = Person::from_args(&args.on, &runs)?;
    let worlds = runs
        .iter()
        .map(|r| person.world_for(r, args.on.other_world))
        .collect::<Result<Vec<_>>>()?;
    let gif_needed = !args.no_gif;
    let browser = chromium();
    if gif_needed && browser.is_none() {
        tracing::warn!("no GIF: it is drawn by headless Chromium, and none was found (Debian: apt-get install chromium, as deploy/setup.sh does; PBRL_CHROMIUM names another); the HTML file is written alone");
    }
    let html = args
        .html
        .clone()
        .unwrap_or_else(|| runs[0].policy.folder.join("watch.html"));
    let gif = args
        .gif
        .clone()
        .unwrap_or_else(|| html.with_extension("gif"));
    let names: Vec<String> = if runs.len() == 1 {
        vec![runs[0].name.clone(), runs[0].name.clone()]
    } else {
        runs.iter().map(|r| r.name.clone()).collect()
    };
    let person_name = person.shown(&worlds[0]);
    let title = if runs.len() == 1 {
        format!("{} for {person_name}", runs[0].name)
    } else {
        format!("{} beside {} for {person_name}", runs[0].name, runs[1].name)
    };
    let info = runs
        .iter()
        .map(|r| format!("{}: checkpoint at {} env steps", r.name, r.policy.env_steps))
        .collect::<Vec<_>>()
        .join(" · ");
    let pairs = pairs(&args, &runs, &worlds)?;
    let mut data =
        serde_json::json!({ "title": title, "info": info, "names": names, "pairs": pairs });
    let page = page_with(&data)?;
    for f in [&html, &gif] {
        if let Some(dir) = f.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        }
    }
    std::fs::write(&html, &page).with_context(|| format!("writing {}", html.display()))?;
    println!(
        "{}: {} episode pairs, opens in any browser",
        html.display(),
        args.episodes
    );
    if let (true, Some(browser)) = (gif_needed, browser) {
        data["capture"] = serde_json::json!({ "step": args.step, "width": args.width });
        let dir = tempfile_dir()?;
        let capture_page = dir.join("capture.html");
        std::fs::write(&capture_page, page_with(&data)?)
            .with_context(|| format!("writing {}", capture_page.display()))?;
        eprintln!(
            "drawing the GIF's frames in headless Chromium ({})...",
            browser.display()
        );
        let frames = capture(&browser, &capture_page);
        let _ = std::fs::remove_dir_all(&dir);
        let frames = frames?;
        write_gif(&frames, &gif)?;
        println!(
            "{}: {} frames, {}x{}, {} ms each",
            gif.display(),
            frames.rgba.len(),
            frames.width,
            frames.height,
            frames.delay_ms
        );
    }
    Ok(())
}

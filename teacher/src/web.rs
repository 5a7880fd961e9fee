//! The labelling page and its HTTP/JSON API (version [`PROTOCOL`]), served by the human
//! teacher. The page is an HTML file, its style sheet and three scripts ([`ASSETS`]) with no
//! build step; any client can use the API instead (`deploy/label.py` is one). The API
//! changes nothing but answers.
//!
//! ```text
//! GET  /                                   the page
//! GET  /label.css, /label.js, /label-draw.js, /label-start.js   its style sheet and scripts
//! GET  /api/v1/status?labeller=NAME        open queries, answers of NAME, budget left, ...
//! GET  /api/v1/next?labeller=NAME[&exclude=ID]   a pair to judge ("kind": "pair", "left",
//!                                          "right") or attempts to rank ("kind": "rank",
//!                                          "attempts": [...]) (200), or none open (204)
//! POST /api/v1/answer {"labeller", "query", "choice": left|right|equal|skip,
//!                      "took_ms", "replays": [left, right]}
//!                     or, for a ranking, "places": [p0, p1, ...] in the order shown
//!                     (0 the best, ties sharing a place) instead of the choice
//! POST /api/v1/undo   {"labeller"}         withdraw NAME's last answer (within undo_s)
//! ```
//!
//! Errors are 4xx with `{"error": "..."}`: 400 malformed, 401 no or wrong token, 404 unknown
//! query, 409 answered already or nothing to undo, 413 a body over 16 KB. With a token,
//! every API call carries `Authorization: Bearer TOKEN`.

use std::collections::VecDeque;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use anyhow::{bail, Context, Result};
use axum::body::Bytes;
use axum::extract::{DefaultBodyLimit, Query as UrlQuery, Request, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::middleware::{self, Next};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use pbrl_actor::replay::{readout, scene, watch, Scene};
use pbrl_actor::WorldConfig;
use pbrl_common::wire::Shown as ShownTrajectory;
use serde::Deserialize;

use crate::human::{Choice, Desk, Refused, Verdict};
use crate::teacher::lock;

/// The API's version.
pub const PROTOCOL: u32 = 1;

/// The largest request body read.
const MAX_BODY: usize = 16 << 10;

/// The page: its HTML, which loads the files of [`ASSETS`] beside it.
const PAGE: &str = include_str!("../assets/label.html");

/// The page's style sheet and scripts (in the order the page loads them), served beside it
/// under these names: (name, content type, text). Built into the binary like the page.
pub const ASSETS: [(&str, &str, &str); 4] = [
    (
        "label.css",
        "text/css; charset=utf-8",
        include_str!("../assets/label.css"),
    ),
    (
        "label.js",
        "text/javascript; charset=utf-8",
        include_str!("../assets/label.js"),
    ),
    (
        "label-draw.js",
        "text/javascript; charset=utf-8",
        include_str!("../assets/label-draw.js"),
    ),
    (
        "label-start.js",
        "text/javascript; charset=utf-8",
        include_str!("../assets/label-start.js"),
    ),
];

/// The page as one file with its style sheet and scripts inline, and `before_scripts` (an
/// element) just before its first script: what `pbrl watch` writes, with its episodes in
/// `before_scripts`.
pub fn page_inline(before_scripts: &str) -> Result<String> {
    let mut page = PAGE.to_string();
    for (i, (name, _, text)) in ASSETS.iter().enumerate() {
        let (tag, inline) = if name.ends_with(".css") {
            (
                format!("<link rel=\"stylesheet\" href=\"{name}\">"),
                format!("<style>\n{text}</style>"),
            )
        } else {
            (
                format!("<script src=\"{name}\"></script>"),
                format!("<script>\n{text}</script>"),
            )
        };
        // NOTE: "</" would end the inline element early; the assets hold none.
        if text.contains("</style") || text.contains("</script") {
            bail!("{name} holds an end tag: it cannot go inline");
        }
        let Some(at) = page.find(&tag) else {
            bail!("the labelling page does not load {name} ({tag})");
        };
        let first_script = ASSETS.iter().position(|(n, _, _)| n.ends_with(".js")) == Some(i);
        let before = if first_script { before_scripts } else { "" };
        page.replace_range(at..at + tag.len(), &format!("{before}{inline}"));
    }
    Ok(page)
}

/// Where and how the page listens. Each default is its flag's.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize, clap::Args)]
pub struct HttpConfig {
    /// Human teacher: where the labelling page listens (loopback unless a --token is set).
    #[arg(long = "http", default_value = "127.0.0.1:8080")]
    pub addr: SocketAddr,
    /// Human teacher: the access token every API call must carry (needed beyond loopback;
    /// default: the PBRL_TOKEN environment variable).
    #[arg(long)]
    pub token: Option<String>,
    /// Human teacher: serve the page over HTTPS with this certificate (PEM; needed beyond
    /// loopback; `deploy/certs.sh page:NAME@IP` makes one).
    #[arg(long, value_name = "FILE", requires = "https_key")]
    pub https_cert: Option<PathBuf>,
    /// Human teacher: the private key of --https-cert (PEM).
    #[arg(long, value_name = "FILE", requires = "https_cert")]
    pub https_key: Option<PathBuf>,
}

impl Default for HttpConfig {
    fn default() -> Self {
        pbrl_common::flags::defaults()
    }
}

impl HttpConfig {
    /// The token: the flag's, else the PBRL_TOKEN environment variable's (if not empty).
    pub fn with_env_token(mut self) -> Self {
        if self.token.is_none() {
            self.token = std::env::var("PBRL_TOKEN").ok().filter(|t| !t.is_empty());
        }
        self
    }

    /// Refuse a bind beyond loopback without a token and HTTPS, and half of the HTTPS pair.
    pub fn validate(&self) -> Result<()> {
        match (&self.https_cert, &self.https_key) {
            (Some(_), None) => {
                bail!("--https-cert needs --https-key (the certificate's private key)")
            }
            (None, Some(_)) => bail!("--https-key needs --https-cert (the page's certificate)"),
            _ => {}
        }
        if self.addr.ip().is_loopback() {
            return Ok(());
        }
        if self.token.as_deref().is_none_or(str::is_empty) {
            bail!(
                "--http {}: listening beyond loopback needs an access token (--token) and HTTPS (--https-cert, --https-key; docs/deploy.md)",
                self.addr
            );
        }
        if self.https_cert.is_none() {
            bail!(
                "--http {}: listening beyond loopback needs HTTPS: give --https-cert and --https-key (deploy/certs.sh makes them; docs/deploy.md)",
                self.addr
            );
        }
        Ok(())
    }

    /// The URL scheme the page is served with.
    pub fn scheme(&self) -> &'static str {
        if self.https_cert.is_some() {
            "https"
        } else {
            "http"
        }
    }

    /// The TLS acceptor of `https_cert` and `https_key` (`None`: plain HTTP).
    fn acceptor(&self) -> Result<Option<tokio_rustls::TlsAcceptor>> {
        use tokio_rustls::rustls::pki_types::pem::PemObject;
        use tokio_rustls::rustls::pki_types::{CertificateDer, PrivateKeyDer};
        let (Some(cert), Some(key)) = (&self.https_cert, &self.https_key) else {
            return Ok(None);
        };
        let chain: Vec<CertificateDer> = CertificateDer::pem_file_iter(cert)
            .and_then(|it| it.collect::<Result<_, _>>())
            .map_err(|e| anyhow::anyhow!("--https-cert {}: {e}", cert.display()))?;
        if chain.is_empty() {
            bail!(
                "--https-cert {}: no certificate in the file",
                cert.display()
            );
        }
        let private = PrivateKeyDer::from_pem_file(key)
            .map_err(|e| anyhow::anyhow!("--https-key {}: {e}", key.display()))?;
        // NOTE: ring, as zenoh's TLS uses (aws-lc would need a C toolchain with cmake); its
        // provider lacks only the post-quantum key exchange, which browsers fall back from.
        #[allow(deprecated)]
        let provider = Arc::new(tokio_rustls::rustls::crypto::ring::default_provider());
        let mut tls = tokio_rustls::rustls::ServerConfig::builder_with_provider(provider)
            .with_safe_default_protocol_versions()
            .context("TLS protocol versions")?
            .with_no_client_auth()
            .with_single_cert(chain, private)
            .with_context(|| {
                format!(
                    "--https-cert {} with --https-key {}",
                    cert.display(),
                    key.display()
                )
            })?;
        tls.alpn_protocols = vec![b"http/1.1".to_vec()];
        Ok(Some(tokio_rustls::TlsAcceptor::from(Arc::new(tls))))
    }
}

/// A query's attempts, drawn.
type Drawn = (u64, Arc<Vec<Scene>>);

/// A refusal: its status and message (`{"error": ...}`).
struct Bad(StatusCode, String);

impl IntoResponse for Bad {
    fn into_response(self) -> Response {
        error(self.0, self.1)
    }
}

/// What the handlers share.
#[derive(Clone)]
pub struct Web {
    pub desk: Arc<Mutex<Desk>>,
    world: Arc<WorldConfig>,
    token: Option<Arc<str>>,
    /// Drawn pairs by query id (the newest few): a page asks for the same pair again.
    scenes: Arc<Mutex<VecDeque<Drawn>>>,
}

impl Web {
    pub fn new(desk: Arc<Mutex<Desk>>, world: WorldConfig, token: Option<String>) -> Self {
        Self {
            desk,
            world: Arc::new(world),
            token: token.map(Arc::from),
            scenes: Arc::default(),
        }
    }
}

fn error(status: StatusCode, msg: impl Into<String>) -> Response {
    (status, Json(serde_json::json!({ "error": msg.into() }))).into_response()
}

fn refused(r: Refused) -> Response {
    let status = match r {
        Refused::Unknown(_) => StatusCode::NOT_FOUND,
        Refused::Answered(_) | Refused::AnsweredByOther(_) | Refused::NothingToUndo => {
            StatusCode::CONFLICT
        }
        Refused::Invalid(_) => StatusCode::BAD_REQUEST,
        Refused::Failed(_) => StatusCode::INTERNAL_SERVER_ERROR,
    };
    // NOTE: a client that sent an answer again (a dropped reply) may take "by_you" as done;
    // an answer that lost the race to another labeller is not recorded.
    let by_you = match r {
        Refused::Answered(_) => Some(true),
        Refused::AnsweredByOther(_) => Some(false),
        _ => None,
    };
    let body = serde_json::json!({ "error": r.to_string(), "by_you": by_you });
    (status, Json(body)).into_response()
}

fn authorised(web: &Web, headers: &HeaderMap) -> Result<(), Bad> {
    let Some(token) = &web.token else {
        return Ok(());
    };
    let given = headers
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.strip_prefix("Bearer "));
    // NOTE: compared in constant time: the token guards a person's labels.
    let same = given.is_some_and(|g| {
        g.len() == token.len()
            && g.bytes()
                .zip(token.bytes())
                .fold(0u8, |acc, (a, b)| acc | (a ^ b))
                == 0
    });
    if same {
        Ok(())
    } else {
        Err(Bad(
            StatusCode::UNAUTHORIZED,
            "missing or wrong access token (Authorization: Bearer TOKEN)".into(),
        ))
    }
}

/// The router of the page and the API (every API call checked for the token first).
pub fn router(web: Web) -> Router {
    let api = Router::new()
        .route("/api/v1/status", get(status))
        .route("/api/v1/next", get(next))
        .route("/api/v1/answer", post(answer))
        .route("/api/v1/undo", post(undo))
        .route_layer(middleware::from_fn_with_state(web.clone(), guard));
    pages()
        .merge(api)
        .layer(DefaultBodyLimit::max(MAX_BODY))
        .with_state(web)
}

/// The page and its [`ASSETS`], each on its own route with its content type.
fn pages<S: Clone + Send + Sync + 'static>() -> Router<S> {
    let mut pages = Router::new().route("/", get(page));
    for (name, kind, text) in ASSETS {
        pages = pages.route(&format!("/{name}"), get(move || asset(kind, text)));
    }
    pages
}

/// Let an API call through only with the token, when there is one.
async fn guard(State(web): State<Web>, req: Request, next: Next) -> Response {
    match authorised(&web, req.headers()) {
        Ok(()) => next.run(req).await,
        Err(r) => r.into_response(),
    }
}

async fn page() -> impl IntoResponse {
    ([(header::CACHE_CONTROL, "no-store")], Html(PAGE))
}

/// One of the page's [`ASSETS`], not cached either: a page and its scripts always come
/// from the same build.
async fn asset(kind: &'static str, text: &'static str) -> impl IntoResponse {
    (
        [
            (header::CONTENT_TYPE, kind),
            (header::CACHE_CONTROL, "no-store"),
        ],
        text,
    )
}

#[derive(Deserialize)]
struct Who {
    labeller: Option<String>,
    exclude: Option<u64>,
}

async fn status(State(web): State<Web>, UrlQuery(who): UrlQuery<Who>) -> Response {
    let mut desk = lock(&web.desk);
    if let Some(l) = who.labeller.as_deref() {
        desk.seen(l);
    }
    Json(status_json(&desk, who.labeller.as_deref())).into_response()
}

/// What a page shows: this person's answers since the desk started, the open queries,
/// the learner's budget left, whether it trains and waits for labels, who labels.
fn status_json(desk: &Desk, labeller: Option<&str>) -> serde_json::Value {
    let learner = desk.learner();
    let fresh = learner.map(|(s, _)| s);
    let mut people = desk.present();
    people.sort();
    let (run, teacher) = desk.names();
    serde_json::json!({
        "protocol": PROTOCOL,
        "run": run,
        "teacher": teacher,
        "open": desk.open_queries(),
        "answered": labeller.map_or(0, |l| desk.answered_by(l)),
        "budget_left": fresh.map(|s| s.budget_left),
        "training": learner.is_some_and(|(_, training)| training),
        "env_steps": fresh.map(|s| s.env_steps),
        "waiting": fresh.is_some_and(|s| s.waiting),
        "held": fresh.is_some_and(|s| s.held),
        "agreement": fresh.and_then(|s| s.agreement),
        "agreement_of": fresh.map_or(0, |s| s.agreement_of),
        "labellers": people,
    })
}

/// Replay a query's side and check that the replay is the episode the learner sent (every
/// step's truth, the segment's among them); keep the segment and its lead-in, with what a
/// person would feel or see at each frame.
fn draw(world: &WorldConfig, s: &ShownTrajectory) -> Result<Scene> {
    let (t, food) = watch(world, s.seed, &s.actions)?;
    let differs = t
        .rewards
        .iter()
        .zip(&s.truth)
        .any(|(r, truth)| (r.truth - truth).abs() > 1e-3 * (1.0 + truth.abs()));
    if differs || t.steps() != s.steps() {
        bail!(
            "the replay of trajectory {} (seed {}) is not the episode the learner sent: the teacher's world config differs from the actors'",
            s.id,
            s.seed
        );
    }
    let mut drawn = scene(&t, world)?;
    drawn.readout = readout(&t, &food)?;
    let seg = s.segment();
    if seg.len() < s.steps() {
        drawn.cut(seg.start, seg.len(), LEAD_IN_STEPS);
    }
    Ok(drawn)
}

/// Steps of the episode shown before a segment (a second at the world's 10 steps a
/// second), so that a person sees where the judged part starts.
pub const LEAD_IN_STEPS: usize = 10;

async fn next(State(web): State<Web>, UrlQuery(who): UrlQuery<Who>) -> Response {
    let Some(labeller) = who.labeller else {
        return error(StatusCode::BAD_REQUEST, "labeller: a name is needed");
    };
    let shown = match lock(&web.desk).next(&labeller, who.exclude) {
        Ok(Some(s)) => s,
        Ok(None) => return StatusCode::NO_CONTENT.into_response(),
        Err(r) => return refused(r),
    };
    let id = shown.query.id;
    let cached = web
        .scenes
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .iter()
        .find(|(q, _)| *q == id)
        .map(|(_, s)| s.clone());
    let scenes = match cached {
        Some(s) => s,
        None => {
            let world = web.world.clone();
            let q = shown.query.clone();
            let drawn = tokio::task::spawn_blocking(move || -> Result<Vec<Scene>> {
                q.attempts().map(|a| draw(&world, a)).collect()
            })
            .await;
            let scenes = match drawn {
                Ok(Ok(s)) => Arc::new(s),
                Ok(Err(e)) => {
                    tracing::warn!(query = id, error = %format!("{e:#}"), "cannot draw a query");
                    return error(StatusCode::INTERNAL_SERVER_ERROR, format!("{e:#}"));
                }
                Err(e) => return error(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()),
            };
            let mut cache = web.scenes.lock().unwrap_or_else(|e| e.into_inner());
            cache.push_back((id, scenes.clone()));
            if cache.len() > 16 {
                cache.pop_front();
            }
            scenes
        }
    };
    if scenes.len() > 2 {
        // A ranking: every attempt, in the order this person is shown them.
        let attempts: Vec<&Scene> = shown.order.iter().map(|&k| &scenes[k]).collect();
        return Json(serde_json::json!({
            "query": id,
            "display": shown.display,
            "kind": "rank",
            "steps": attempts.iter().map(|s| s.steps).max().unwrap_or(0),
            "attempts": attempts,
        }))
        .into_response();
    }
    let (left, right) = if shown.swapped {
        (&scenes[1], &scenes[0])
    } else {
        (&scenes[0], &scenes[1])
    };
    Json(serde_json::json!({
        "query": id,
        "display": shown.display,
        "kind": "pair",
        "steps": left.steps.max(right.steps),
        "left": left,
        "right": right,
    }))
    .into_response()
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct AnswerBody {
    labeller: String,
    query: u64,
    /// A pair's answer (or skip for either kind).
    #[serde(default)]
    choice: Option<Choice>,
    /// A ranking's answer: each attempt's place in the order shown (0 the best).
    #[serde(default)]
    places: Option<Vec<u8>>,
    #[serde(default)]
    took_ms: u64,
    #[serde(default)]
    replays: [u32; 2],
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct UndoBody {
    labeller: String,
}

fn parse<T: serde::de::DeserializeOwned>(headers: &HeaderMap, body: &Bytes) -> Result<T, Bad> {
    let json = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("application/json"));
    if !json {
        return Err(Bad(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "the body must be JSON (Content-Type: application/json)".into(),
        ));
    }
    serde_json::from_slice(body)
        .map_err(|e| Bad(StatusCode::BAD_REQUEST, format!("malformed body: {e}")))
}

async fn answer(State(web): State<Web>, headers: HeaderMap, body: Bytes) -> Response {
    let a: AnswerBody = match parse(&headers, &body) {
        Ok(a) => a,
        Err(r) => return r.into_response(),
    };
    // NOTE: a person needs an hour at most per pair; anything longer is a broken clock.
    let took_ms = a.took_ms.min(3_600_000);
    let replays = a.replays.map(|r| r.min(1000));
    let verdict =
        match (a.choice, a.places) {
            (Some(c), None) => Verdict::Choice(c),
            (None, Some(p)) => Verdict::Places(p),
            _ => return error(
                StatusCode::BAD_REQUEST,
                "choice or places: give exactly one (a choice for a pair, places for a ranking)",
            ),
        };
    match lock(&web.desk).give(&a.labeller, a.query, verdict, took_ms, replays) {
        Ok(answered) => {
            Json(serde_json::json!({ "ok": true, "answered": answered })).into_response()
        }
        Err(r) => refused(r),
    }
}

async fn undo(State(web): State<Web>, headers: HeaderMap, body: Bytes) -> Response {
    let u: UndoBody = match parse(&headers, &body) {
        Ok(u) => u,
        Err(r) => return r.into_response(),
    };
    match lock(&web.desk).undo(&u.labeller) {
        Ok(query) => Json(serde_json::json!({ "query": query })).into_response(),
        Err(r) => refused(r),
    }
}

/// The page's socket, bound, with its TLS (checked first: beyond loopback only with a
/// token and HTTPS; the certificate and key are read here, so a bad file fails at start).
pub struct Bound {
    pub listener: tokio::net::TcpListener,
    tls: Option<tokio_rustls::TlsAcceptor>,
}

/// Bind the page's address.
pub async fn bind(cfg: &HttpConfig) -> Result<Bound> {
    cfg.validate()?;
    let tls = cfg.acceptor()?;
    let listener = tokio::net::TcpListener::bind(cfg.addr)
        .await
        .with_context(|| format!("listening on {} for the labelling page", cfg.addr))?;
    Ok(Bound { listener, tls })
}

/// Serve `app` on `bound` (over TLS where it has a certificate) until `shutdown`.
pub async fn serve(
    bound: Bound,
    app: Router,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    let Some(tls) = bound.tls else {
        return axum::serve(bound.listener, app)
            .with_graceful_shutdown(shutdown)
            .await;
    };
    tokio::pin!(shutdown);
    loop {
        let (tcp, peer) = tokio::select! {
            _ = &mut shutdown => return Ok(()),
            a = bound.listener.accept() => match a {
                Ok(a) => a,
                Err(e) => {
                    // NOTE: out of file descriptors and the like: the next accept may work.
                    tracing::warn!(error = %e, "the labelling page could not accept a connection");
                    tokio::time::sleep(std::time::Duration::from_millis(100)).await;
                    continue;
                }
            },
        };
        let (tls, app) = (tls.clone(), app.clone());
        tokio::spawn(async move {
            // NOTE: a client that does not speak TLS (plain HTTP to the HTTPS port) or does
            // not trust the certificate fails its handshake here, seeing nothing.
            let stream = match tls.accept(tcp).await {
                Ok(s) => s,
                Err(e) => {
                    tracing::debug!(%peer, error = %e, "a TLS handshake at the labelling page failed");
                    return;
                }
            };
            let service = hyper_util::service::TowerToHyperService::new(app);
            if let Err(e) = hyper::server::conn::http1::Builder::new()
                .serve_connection(hyper_util::rt::TokioIo::new(stream), service)
                .await
            {
                tracing::debug!(%peer, error = %e, "an HTTPS connection at the labelling page ended");
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use pbrl_actor::controller::{Controller, ControllerKind};
    use pbrl_actor::rollout::run_episode;
    use pbrl_actor::FeedingWorld;

    /// One side of a query showing steps `start .. start + len` of a random episode.
    fn side(world: &WorldConfig, seed: u64, start: u32, len: u32) -> ShownTrajectory {
        let mut w = FeedingWorld::new(world.clone()).unwrap();
        let mut c = Controller::new(ControllerKind::Random);
        let t = run_episode(&mut w, &mut c, seed).unwrap();
        ShownTrajectory {
            id: 1,
            seed,
            policy_version: 1,
            act_dim: t.act_dim,
            actions: t.actions.clone(),
            truth: t.rewards.iter().map(|r| r.truth).collect(),
            replay: None,
            start,
            len,
        }
    }

    #[test]
    fn a_segment_is_replayed_from_its_seed_and_shown_with_its_lead_in() {
        let world = WorldConfig::default();
        let s = side(&world, 5, 120, 50);
        let scene = draw(&world, &s).unwrap();
        assert_eq!(scene.steps, LEAD_IN_STEPS + 50);
        assert_eq!(scene.segment_from, LEAD_IN_STEPS);
        assert_eq!(scene.frames.spoon.len(), LEAD_IN_STEPS + 51);
        // The frames are the episode's own: the same as the whole replay's, cut.
        let whole = draw(
            &world,
            &ShownTrajectory {
                start: 0,
                len: 200,
                ..s.clone()
            },
        )
        .unwrap();
        assert_eq!(whole.segment_from, 0);
        assert_eq!(scene.frames.spoon[..], whole.frames.spoon[110..=170]);
        // What the strips show is cut with the frames.
        assert_eq!(whole.readout.distance.len(), 201);
        assert_eq!(
            scene.readout.distance[..],
            whole.readout.distance[110..=170]
        );
        assert_eq!(scene.readout.food[..], whole.readout.food[110..=170]);
        // A segment at the start has what lead-in there is.
        let early = draw(
            &world,
            &ShownTrajectory {
                start: 3,
                ..s.clone()
            },
        )
        .unwrap();
        assert_eq!((early.segment_from, early.steps), (3, 53));
        // A truth that is not the episode's, in the segment, is refused.
        let mut wrong = s.clone();
        wrong.truth[130] += 1.0;
        let e = draw(&world, &wrong).unwrap_err();
        assert!(
            format!("{e:#}").contains("not the episode the learner sent"),
            "{e:#}"
        );
    }

    #[test]
    fn the_inline_page_holds_every_asset_and_loads_none() {
        let page = page_inline("<script id=\"data\"></script>\n").unwrap();
        for (name, _, text) in ASSETS {
            assert!(page.contains(text), "{name} is not inline");
            assert!(
                !page.contains(&format!("\"{name}\"")),
                "{name} is still loaded"
            );
        }
        let data = page.find("<script id=\"data\">").unwrap();
        let first = page.find(ASSETS[1].2).unwrap();
        assert!(data < first, "the data comes after the first script");
        assert!(
            page.find(ASSETS[0].2).unwrap() < data,
            "the style sheet stays in the head"
        );
    }

    /// `GET path` from `addr`, one request on its own connection: the reply's head and body.
    fn get_raw(addr: std::net::SocketAddr, path: &str) -> (String, String) {
        use std::io::{Read, Write};
        let mut s = std::net::TcpStream::connect(addr).unwrap();
        write!(
            s,
            "GET {path} HTTP/1.1\r\nHost: page\r\nConnection: close\r\n\r\n"
        )
        .unwrap();
        let mut reply = String::new();
        s.read_to_string(&mut reply).unwrap();
        let (head, body) = reply.split_once("\r\n\r\n").unwrap();
        (head.to_ascii_lowercase(), body.to_string())
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn the_page_and_its_files_are_served_with_their_types_and_not_cached() {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        tokio::spawn(async move { axum::serve(listener, pages::<()>()).await });
        let mut want = vec![("/".to_string(), "text/html; charset=utf-8", PAGE)];
        want.extend(ASSETS.iter().map(|(n, k, t)| (format!("/{n}"), *k, *t)));
        for (path, kind, text) in want {
            let (head, body) = tokio::task::spawn_blocking(move || get_raw(addr, &path))
                .await
                .unwrap();
            assert!(head.starts_with("http/1.1 200"), "{head}");
            assert!(head.contains(&format!("content-type: {kind}")), "{head}");
            assert!(head.contains("cache-control: no-store"), "{head}");
            assert_eq!(body, text);
        }
        let (head, _) = tokio::task::spawn_blocking(move || get_raw(addr, "/label.json"))
            .await
            .unwrap();
        assert!(head.starts_with("http/1.1 404"), "{head}");
    }
}

//! ESIM-style event generation: per-pixel log intensity, linearly interpolated in time between two
//! rendered frames, fires an event each time it moves a contrast threshold away from the pixel's
//! reference level.
//!
//! Model per pixel (state `d = L − reference`):
//! - `L = ln(I + log_eps)` with `I` the linear intensity. The epsilon keeps black (space background)
//!   finite and makes the response linear rather than logarithmic for `I ≪ log_eps`, like the
//!   photoreceptor of a real sensor; it also stops quantisation-level flicker on black from producing
//!   events.
//! - Between frames `L` is linear in time, so `d` grows at the constant rate `ΔL/Δt + leak`. An ON
//!   event fires when `d` reaches `C_on`, an OFF event when it reaches `−C_off`, at the interpolated
//!   crossing time; `d` then resets to 0 (the reference becomes the current level).
//! - Thresholds carry per-pixel mismatch: `C ~ N(C_nominal, σ)` drawn once per seed, floored at
//!   [`C_MIN`].
//! - Refractory period `R`: after an event the pixel is held in reset (`d = 0`, the reference follows
//!   `L`) until `t + R`. With `R = 0` this is exactly classic ESIM.
//! - Leak: the reference drifts down at `leak_rate_hz · C_on` per second (ON events in a static scene).
//!
//! Each frame interval is processed in parallel over pixel rows; random draws come from a per-(frame,
//! row) stream, and the merged output is stably sorted by `(t, pixel index)`, so the stream depends
//! only on the seed and the frames, never on the number of threads.

use rayon::prelude::*;

use super::noise::{poisson_events, shot_noise_row, NoiseConfig};
use super::rng::Rng;
use crate::error::{Error, Result};
use crate::events::Events;

/// Per-pixel thresholds drawn below this are clamped to it (a non-positive threshold is meaningless).
pub const C_MIN: f64 = 0.01;

/// |ΔL| below this counts as unchanged in [`EventSimulator::log_change_quantile`] (renderer rounding).
pub const CHANGE_FLOOR: f32 = 1e-4;

/// Stream index of the draws made once at construction (thresholds, hot pixels); frame `k` uses `k + 1`.
const SETUP_STREAM: u64 = 0;

/// Simulator parameters (thresholds in natural-log units, times in µs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EsimConfig {
    pub c_on: f64,
    pub c_off: f64,
    /// Standard deviation of the per-pixel threshold mismatch.
    pub sigma_c: f64,
    pub refractory_us: f64,
    /// Added to the linear intensity before the logarithm (see the module docs).
    pub log_eps: f64,
    pub noise: NoiseConfig,
    pub seed: u64,
}

impl Default for EsimConfig {
    fn default() -> Self {
        EsimConfig {
            c_on: 0.2,
            c_off: 0.2,
            sigma_c: 0.0,
            refractory_us: 0.0,
            log_eps: 1e-3,
            noise: NoiseConfig::default(),
            seed: 0,
        }
    }
}

impl EsimConfig {
    pub fn validate(&self) -> Result<()> {
        if !(self.c_on >= C_MIN && self.c_off >= C_MIN && self.c_on.is_finite() && self.c_off.is_finite()) {
            return Err(Error::Invalid(format!("contrast thresholds must be ≥ {C_MIN} and finite")));
        }
        if !(self.sigma_c >= 0.0 && self.sigma_c.is_finite()) {
            return Err(Error::Invalid("sigma_c must be ≥ 0".into()));
        }
        if !(self.refractory_us >= 0.0 && self.refractory_us.is_finite()) {
            return Err(Error::Invalid("refractory_us must be ≥ 0".into()));
        }
        if !(self.log_eps > 0.0 && self.log_eps.is_finite()) {
            return Err(Error::Invalid("log_eps must be > 0".into()));
        }
        self.noise.validate()
    }
}

/// One event while a row is being processed: pixel index instead of (x, y).
#[derive(Debug, Clone, Copy)]
struct PixelEvent {
    t: i64,
    idx: u32,
    p: i8,
}

/// The simulator: feed frames in time order with [`push_frame`](Self::push_frame), collect the events
/// with [`take_events`](Self::take_events).
#[derive(Debug)]
pub struct EventSimulator {
    cfg: EsimConfig,
    width: u32,
    height: u32,
    c_on: Vec<f32>,
    c_off: Vec<f32>,
    hot: Vec<bool>,
    /// Log and linear intensity of the last frame.
    log: Vec<f32>,
    lin: Vec<f32>,
    /// `L − reference` per pixel.
    d: Vec<f64>,
    /// End of the refractory period per pixel (µs).
    hold: Vec<f64>,
    t_prev: Option<i64>,
    frame: u64,
    events: Events,
    /// Events at exactly the last frame time: the next interval may add more at that instant, so they
    /// wait to be sorted together (global order by `(t, pixel index)`).
    pending: Vec<PixelEvent>,
}

impl EventSimulator {
    pub fn new(width: u32, height: u32, cfg: EsimConfig) -> Result<Self> {
        cfg.validate()?;
        if width == 0 || height == 0 || width > u32::from(u16::MAX) + 1 || height > u32::from(u16::MAX) + 1 {
            return Err(Error::Invalid(format!("sensor size {width}x{height} is not supported")));
        }
        let (w, n) = (width as usize, width as usize * height as usize);
        let mut c_on = vec![0f32; n];
        let mut c_off = vec![0f32; n];
        let mut hot = vec![false; n];
        c_on.par_chunks_mut(w).zip(c_off.par_chunks_mut(w)).zip(hot.par_chunks_mut(w)).enumerate().for_each(
            |(y, ((on, off), hot))| {
                let mut rng = Rng::new(cfg.seed, SETUP_STREAM, y as u64);
                for x in 0..w {
                    on[x] = (cfg.c_on + cfg.sigma_c * rng.normal()).max(C_MIN) as f32;
                    off[x] = (cfg.c_off + cfg.sigma_c * rng.normal()).max(C_MIN) as f32;
                    hot[x] = rng.uniform() < cfg.noise.hot_pixel_fraction;
                }
            },
        );
        Ok(EventSimulator {
            cfg,
            width,
            height,
            c_on,
            c_off,
            hot,
            log: Vec::new(),
            lin: Vec::new(),
            d: vec![0.0; n],
            hold: vec![f64::NEG_INFINITY; n],
            t_prev: None,
            frame: 0,
            events: Events::with_capacity(0, width, height),
            pending: Vec::new(),
        })
    }

    pub fn config(&self) -> &EsimConfig {
        &self.cfg
    }

    /// Number of pixels marked hot for this seed.
    pub fn hot_pixel_count(&self) -> usize {
        self.hot.iter().filter(|&&h| h).count()
    }

    /// Events generated so far and not yet taken.
    pub fn num_events(&self) -> usize {
        self.events.len() + self.pending.len()
    }

    /// Time of the last frame pushed (µs), if any.
    pub fn last_time(&self) -> Option<i64> {
        self.t_prev
    }

    /// Hand over the events generated so far (sorted by t, ties by pixel index).
    pub fn take_events(&mut self) -> Events {
        let pending = std::mem::take(&mut self.pending);
        self.append(&pending);
        std::mem::replace(&mut self.events, Events::with_capacity(0, self.width, self.height))
    }

    fn check_frame(&self, t_us: i64, frame: &[f32]) -> Result<()> {
        let n = self.width as usize * self.height as usize;
        if frame.len() != n {
            return Err(Error::Invalid(format!(
                "frame at t={t_us} µs has {} pixels, expected {}x{} = {n}",
                frame.len(),
                self.width,
                self.height
            )));
        }
        if let Some(tp) = self.t_prev {
            if t_us <= tp {
                return Err(Error::Invalid(format!(
                    "frame at t={t_us} µs is not after the previous one ({tp} µs)"
                )));
            }
        }
        if let Some(i) = frame.par_iter().position_first(|v| !v.is_finite()) {
            let w = self.width as usize;
            return Err(Error::Invalid(format!(
                "frame at t={t_us} µs: pixel ({}, {}) is not finite",
                i % w,
                i / w
            )));
        }
        Ok(())
    }

    /// Push a linear-intensity frame (row-major, `width × height`, ≥ 0) taken at `t_us`. The first frame
    /// sets the reference levels; each later one generates the events of the interval since the last.
    /// Returns the number of events added.
    pub fn push_frame(&mut self, t_us: i64, intensity: &[f32]) -> Result<usize> {
        self.check_frame(t_us, intensity)?;
        let log = self.to_log(intensity);
        Ok(self.advance(t_us, log, intensity.to_vec()))
    }

    /// Push a frame given directly as log intensity (for analytic signals and tests).
    pub fn push_log_frame(&mut self, t_us: i64, log: &[f32]) -> Result<usize> {
        self.check_frame(t_us, log)?;
        let eps = self.cfg.log_eps as f32;
        let lin: Vec<f32> = log.par_iter().map(|&l| (l.exp() - eps).max(0.0)).collect();
        Ok(self.advance(t_us, log.to_vec(), lin))
    }

    /// Push a linear-intensity frame only if the change since the last frame is smooth enough: the
    /// `q`-quantile of |ΔL| must not exceed `max_change` (see [`Self::change_quantile`]). Returns that
    /// quantile and `Some(events added)`, or `None` with nothing changed when the frame is rejected (the
    /// caller renders a nearer time instead). One log conversion serves both the check and the events.
    pub fn push_frame_if_smooth(
        &mut self,
        t_us: i64,
        intensity: &[f32],
        q: f64,
        min_level: f32,
        max_change: f64,
    ) -> Result<(f64, Option<usize>)> {
        self.check_frame(t_us, intensity)?;
        let log = self.to_log(intensity);
        let change = self.change_quantile(&log, intensity, q, min_level);
        if change > max_change {
            return Ok((change, None));
        }
        Ok((change, Some(self.advance(t_us, log, intensity.to_vec()))))
    }

    fn to_log(&self, intensity: &[f32]) -> Vec<f32> {
        let eps = self.cfg.log_eps as f32;
        intensity.par_iter().map(|&v| (v.max(0.0) + eps).ln()).collect()
    }

    /// The `q`-quantile of |ΔL| from the last frame to (`log`, `lin`), over the pixels that changed (by
    /// more than [`CHANGE_FLOOR`]) and are at least `min_level` bright in both frames; 0 when none (or
    /// when there is no last frame). Drives the adaptive render rate. Silhouettes jumping from black
    /// are excluded, and a quantile rather than the maximum is used, because edges (silhouettes,
    /// texture and facet boundaries) are steps at any frame rate: the driver bounds them by limiting
    /// image motion per frame instead.
    fn change_quantile(&self, log: &[f32], lin: &[f32], q: f64, min_level: f32) -> f64 {
        if self.t_prev.is_none() {
            return 0.0;
        }
        let mut changes: Vec<f32> = (log, lin, &self.log[..], &self.lin[..])
            .into_par_iter()
            .filter_map(|(&l1, &i1, &l0, &i0)| {
                let dl = (l1 - l0).abs();
                (i0 >= min_level && i1 >= min_level && dl > CHANGE_FLOOR).then_some(dl)
            })
            .collect();
        if changes.is_empty() {
            return 0.0;
        }
        let k = ((q.clamp(0.0, 1.0) * (changes.len() - 1) as f64).round()) as usize;
        let (_, v, _) = changes.select_nth_unstable_by(k, f32::total_cmp);
        f64::from(*v)
    }

    fn advance(&mut self, t_us: i64, log: Vec<f32>, lin: Vec<f32>) -> usize {
        let Some(t0) = self.t_prev else {
            self.log = log;
            self.lin = lin;
            self.t_prev = Some(t_us);
            return 0;
        };
        self.frame += 1;
        let w = self.width as usize;
        let (t0f, t1f) = (t0 as f64, t_us as f64);
        let dt = t1f - t0f;
        let cfg = self.cfg;
        let leak = cfg.noise.leak_rate_hz * cfg.c_on * 1e-6; // reference drift per µs
        let refractory = cfg.refractory_us;
        let (old_log, old_lin, c_on, c_off, hot) = (&self.log, &self.lin, &self.c_on, &self.c_off, &self.hot);
        let (new_log, new_lin) = (&log, &lin);
        let frame = self.frame;
        let rows: Vec<Vec<PixelEvent>> = self
            .d
            .par_chunks_mut(w)
            .zip(self.hold.par_chunks_mut(w))
            .enumerate()
            .map(|(y, (d_row, hold_row))| {
                let mut out = Vec::new();
                let mut rng = Rng::new(cfg.seed, frame, y as u64);
                for x in 0..w {
                    let i = y * w + x;
                    let idx = i as u32;
                    let mut emit = |t: f64, p: i8| {
                        out.push(PixelEvent { t: (t.round() as i64).clamp(t0, t_us), idx, p });
                    };
                    let slope = (f64::from(new_log[i]) - f64::from(old_log[i])) / dt + leak;
                    let mut t = t0f;
                    let mut d = d_row[x];
                    if hold_row[x] > t0f {
                        // Still held in reset from an earlier event.
                        t = hold_row[x].min(t1f);
                        d = 0.0;
                    }
                    if t < t1f && slope != 0.0 {
                        let (level, p) =
                            if slope > 0.0 { (f64::from(c_on[i]), 1) } else { (-f64::from(c_off[i]), -1) };
                        loop {
                            let tc = (t + (level - d) / slope).max(t);
                            if tc > t1f {
                                break;
                            }
                            emit(tc, p);
                            d = 0.0;
                            t = tc;
                            if refractory > 0.0 {
                                hold_row[x] = tc + refractory;
                                t = hold_row[x].min(t1f);
                            }
                        }
                    }
                    d_row[x] = d + slope * (t1f - t);
                    if hot[i] {
                        poisson_events(&mut rng, cfg.noise.hot_pixel_rate_hz, t0, t_us, |t, p| {
                            out.push(PixelEvent { t, idx, p })
                        });
                    }
                }
                let row = y * w;
                let mean_intensity =
                    |x: usize| 0.5 * (f64::from(old_lin[row + x]) + f64::from(new_lin[row + x]));
                shot_noise_row(&cfg.noise, &mut rng, w, mean_intensity, t0, t_us, |x, t, p| {
                    out.push(PixelEvent { t, idx: (row + x) as u32, p })
                });
                out
            })
            .collect();
        let added: usize = rows.iter().map(Vec::len).sum();
        let mut merged = std::mem::take(&mut self.pending);
        merged.reserve(added);
        for row in rows {
            merged.extend(row);
        }
        // Stable: events of one pixel at the same µs keep their generation order.
        merged.par_sort_by_key(|e| (e.t, e.idx));
        let split = merged.partition_point(|e| e.t < t_us);
        self.pending = merged.split_off(split);
        self.append(&merged);
        self.log = log;
        self.lin = lin;
        self.t_prev = Some(t_us);
        added
    }

    fn append(&mut self, sorted: &[PixelEvent]) {
        let w = self.width as usize;
        let ev = &mut self.events;
        ev.t.reserve(sorted.len());
        ev.x.reserve(sorted.len());
        ev.y.reserve(sorted.len());
        ev.p.reserve(sorted.len());
        for e in sorted {
            ev.push(e.t, (e.idx as usize % w) as u16, (e.idx as usize / w) as u16, e.p);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Feed a 1-pixel-wide strip the log signals `f(pixel, t)` sampled at `times`.
    fn run(cfg: EsimConfig, n: u32, times: &[i64], f: impl Fn(usize, f64) -> f64) -> Events {
        let mut sim = EventSimulator::new(n, 1, cfg).unwrap();
        for &t in times {
            let frame: Vec<f32> = (0..n as usize).map(|i| f(i, t as f64) as f32).collect();
            sim.push_log_frame(t, &frame).unwrap();
        }
        sim.take_events()
    }

    #[test]
    fn log_linear_ramp_gives_the_expected_events() {
        // L(t) = 0.05 + 1e-3·t (t in µs): crossings of 0.05 + k·0.2 at t = 200·k µs, k = 1..=5.
        let cfg = EsimConfig { c_on: 0.2, c_off: 0.3, ..Default::default() };
        let times: Vec<i64> = (0..=7).map(|k| k * 150).collect(); // frames do not align with crossings
        let ev = run(cfg, 1, &times, |_, t| 0.05 + 1e-3 * t);
        assert_eq!(ev.t, vec![200, 400, 600, 800, 1000]);
        assert!(ev.p.iter().all(|&p| p == 1));
        // Falling: −0.3 per 300 µs with C_off = 0.3 → OFF events every 300 µs.
        let ev = run(cfg, 1, &times, |_, t| -1e-3 * t);
        assert_eq!(ev.t, vec![300, 600, 900]);
        assert!(ev.p.iter().all(|&p| p == -1));
    }

    #[test]
    fn reversal_counts_from_the_reference() {
        // Up by 0.5 (2 ON at C=0.2, reference ends at 0.4), then down to 0.1: the first OFF fires at
        // 0.4 − 0.2 = 0.2, the next would need 0.0 → one OFF event.
        let cfg = EsimConfig { c_on: 0.2, c_off: 0.2, ..Default::default() };
        let ev =
            run(cfg, 1, &[0, 500, 900], |_, t| if t <= 500.0 { 1e-3 * t } else { 0.5 - 1e-3 * (t - 500.0) });
        assert_eq!(ev.p, vec![1, 1, -1]);
        assert_eq!(ev.t, vec![200, 400, 800]);
    }

    #[test]
    fn refractory_period_holds_the_pixel_in_reset() {
        // Crossings every 100 µs without refractory; with R = 250 µs the pixel fires at 100, is blind
        // until 350 (reference = L(350)), fires again at 450, 800, 1150, ...
        let cfg = EsimConfig { c_on: 0.1, refractory_us: 250.0, ..Default::default() };
        let times: Vec<i64> = (0..=12).map(|k| k * 100).collect();
        let ev = run(cfg, 1, &times, |_, t| 1e-3 * t);
        assert_eq!(ev.t, vec![100, 450, 800, 1150]);
    }

    #[test]
    fn static_scene_without_noise_is_silent() {
        let cfg = EsimConfig { sigma_c: 0.05, ..Default::default() };
        let mut sim = EventSimulator::new(32, 8, cfg).unwrap();
        let frame: Vec<f32> = (0..256).map(|i| (i as f32) / 256.0).collect();
        for k in 0..20 {
            sim.push_frame(k * 1000, &frame).unwrap();
        }
        assert!(sim.take_events().is_empty());
    }

    #[test]
    fn leak_fires_on_events_at_the_leak_rate() {
        let noise = NoiseConfig { leak_rate_hz: 10.0, ..Default::default() };
        let cfg = EsimConfig { noise, ..Default::default() };
        // 1.05 s static: the reference drifts by C every 0.1 s → 10 ON events per pixel, at 0.1 s, 0.2 s…
        let times: Vec<i64> = (0..=10).map(|k| k * 105_000).collect();
        let ev = run(cfg, 4, &times, |_, _| 0.0);
        assert_eq!(ev.len(), 40);
        assert!(ev.p.iter().all(|&p| p == 1));
        assert_eq!(ev.t.iter().filter(|&&t| t == 100_000).count(), 4);
    }

    #[test]
    fn shot_noise_is_higher_in_the_dark() {
        let noise = NoiseConfig { shot_rate_hz: 2.0, shot_dark_level: 0.01, ..Default::default() };
        let cfg = EsimConfig { noise, seed: 3, ..Default::default() };
        let mut sim = EventSimulator::new(200, 100, cfg).unwrap();
        // Left half black, right half bright (I = 0.99 → rate 2·0.01/1.0 = 0.02 Hz).
        let frame: Vec<f32> = (0..20_000).map(|i| if i % 200 < 100 { 0.0 } else { 0.99 }).collect();
        for k in 0..=10 {
            sim.push_frame(k * 100_000, &frame).unwrap();
        }
        let ev = sim.take_events();
        let dark = ev.x.iter().filter(|&&x| x < 100).count() as f64;
        let bright = ev.len() as f64 - dark;
        // Expected 10 000 px · 2 Hz · 1 s = 20 000 dark events and ~200 bright ones.
        assert!((dark - 20_000.0).abs() < 5.0 * 20_000f64.sqrt(), "dark {dark}");
        assert!(bright < 400.0, "bright {bright}");
        assert!(ev.view().is_sorted());
        let on = ev.p.iter().filter(|&&p| p == 1).count() as f64;
        assert!((on / ev.len() as f64 - 0.5).abs() < 0.02);
    }

    #[test]
    fn hot_pixels_fire_at_their_rate() {
        let noise = NoiseConfig { hot_pixel_fraction: 0.01, hot_pixel_rate_hz: 100.0, ..Default::default() };
        let mut sim =
            EventSimulator::new(100, 100, EsimConfig { noise, seed: 5, ..Default::default() }).unwrap();
        let hot = sim.hot_pixel_count();
        assert!((50..=150).contains(&hot), "{hot}");
        let frame = vec![0.5f32; 10_000];
        sim.push_frame(0, &frame).unwrap();
        sim.push_frame(1_000_000, &frame).unwrap();
        let n = sim.take_events().len() as f64;
        let expected = hot as f64 * 100.0;
        assert!((n - expected).abs() < 5.0 * expected.sqrt(), "{n} vs {expected}");
    }

    fn textured_run(threads: usize) -> Events {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        pool.install(|| {
            let noise = NoiseConfig {
                shot_rate_hz: 5.0,
                leak_rate_hz: 1.0,
                hot_pixel_fraction: 0.01,
                hot_pixel_rate_hz: 50.0,
                ..Default::default()
            };
            let cfg =
                EsimConfig { sigma_c: 0.03, refractory_us: 50.0, noise, seed: 11, ..Default::default() };
            let (w, h) = (64usize, 48usize);
            let mut sim = EventSimulator::new(w as u32, h as u32, cfg).unwrap();
            for k in 0..30i64 {
                let s = k as f32 * 0.3;
                let frame: Vec<f32> = (0..w * h)
                    .map(|i| 0.5 + 0.4 * ((i % w) as f32 * 0.3 + s).sin() * ((i / w) as f32 * 0.2).cos())
                    .collect();
                sim.push_frame(k * 1000, &frame).unwrap();
            }
            sim.take_events()
        })
    }

    #[test]
    fn output_is_sorted_and_independent_of_thread_count() {
        let a = textured_run(1);
        let b = textured_run(2);
        assert!(a.len() > 1000);
        assert_eq!(a, b);
        let key: Vec<(i64, u32)> =
            (0..a.len()).map(|i| (a.t[i], u32::from(a.y[i]) * 64 + u32::from(a.x[i]))).collect();
        assert!(key.windows(2).all(|w| w[0] <= w[1]));
        assert_ne!(a, EventSimulator::new(1, 1, EsimConfig::default()).unwrap().take_events());
    }

    #[test]
    fn rough_frames_are_refused_and_change_nothing() {
        let cfg = EsimConfig { c_on: 0.1, c_off: 0.1, ..Default::default() };
        let mut sim = EventSimulator::new(4, 1, cfg).unwrap();
        let base = [0.5f32, 0.5, 0.5, 0.0];
        assert_eq!(sim.push_frame_if_smooth(0, &base, 0.5, 0.01, 0.1).unwrap(), (0.0, Some(0)));
        // ΔL = ln 1.2, ln 1.2, ln 3 on the lit pixels (the black one is ignored): median ln 1.2.
        let next = [0.6f32, 0.6, 1.5, 1.0];
        let med = f64::from((0.6f32 + 1e-3).ln() - (0.5f32 + 1e-3).ln());
        let (change, added) = sim.push_frame_if_smooth(1000, &next, 0.5, 0.01, 0.1).unwrap();
        assert!((change - med).abs() < 1e-6 && added.is_none());
        let (change, _) = sim.push_frame_if_smooth(1000, &next, 1.0, 0.01, 10.0).unwrap();
        assert!((change - f64::from((1.5f32 + 1e-3).ln() - (0.5f32 + 1e-3).ln())).abs() < 1e-6);
        // The refused attempt changed nothing: the accepted one above produced the events of 0 → 1000.
        let ev = sim.take_events();
        assert_eq!(ev.len(), 1 + 1 + 10 + 69);
        assert_eq!(sim.last_time(), Some(1000));
    }

    #[test]
    fn bad_frames_are_rejected() {
        let mut sim = EventSimulator::new(2, 2, EsimConfig::default()).unwrap();
        assert!(sim.push_frame(0, &[0.0; 3]).unwrap_err().to_string().contains("expected 2x2"));
        sim.push_frame(10, &[0.0; 4]).unwrap();
        assert!(sim.push_frame(10, &[0.0; 4]).unwrap_err().to_string().contains("not after"));
        let e = sim.push_frame(20, &[0.0, 0.0, f32::NAN, 0.0]).unwrap_err().to_string();
        assert!(e.contains("pixel (0, 1)"), "{e}");
        assert!(EventSimulator::new(2, 2, EsimConfig { c_on: 0.0, ..Default::default() }).is_err());
    }
}

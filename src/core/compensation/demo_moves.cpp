// The demo's tracking_trim scenario (compensation/demo_scenario.h): an operator's moves and holds, and their scores.
#include <algorithm>
#include <cmath>
#include <random>
#include <stdexcept>

#include "piezo_compensation/compensation/demo_scenario.h"

namespace piezo::compensation {
namespace {

// A ramp at `rate` V/s to `goal` (its last sample on the goal), then `hold_s` at the goal; held_s counts from the
// last sample of the ramp.
void move_and_hold(std::vector<DemoStep>& s, int mode, int seg, bool warmup, double& v, double goal, double rate,
                   double hold_s, const char* hold_phase, double hz) {
  const double dt = 1.0 / hz;
  const std::string move = warmup ? "warmup" : "move", held = warmup ? "warmup" : hold_phase;
  while (v != goal) {
    const double step = std::clamp(goal - v, -rate * dt, rate * dt);
    v = std::abs(goal - v - step) < 1e-12 ? goal : v + step;
    s.push_back({mode, seg, move, v, 0.0});
  }
  const int n = static_cast<int>(std::lround(hold_s * hz));
  for (int k = 1; k <= n; ++k) s.push_back({mode, seg, held, v, k * dt});
}

bool moves_scored_as_move(const DemoStep& s, double settle_s) {
  return s.phase == "move" || ((s.phase == "hold" || s.phase == "rest") && s.held_s < settle_s);
}

}  // namespace

std::vector<DemoStep> moves_demo_steps(const MovesDemoOptions& o, double hz) {
  if (o.moves < 1) throw std::invalid_argument("~moves must be >= 1");
  if (!(o.hold_s > 0.0)) throw std::invalid_argument("~hold_s must be > 0 s");
  if (!(o.hold_score_from_s >= 0.0) || o.hold_score_from_s >= o.hold_s)
    throw std::invalid_argument("~hold_score_from_s must be in [0, ~hold_s)");
  if (!(o.rate_min_v_per_s > 0.0) || o.rate_max_v_per_s < o.rate_min_v_per_s || o.target_max_v < o.target_min_v)
    throw std::invalid_argument("moves demo: rates must be > 0 V/s and the ranges ordered");
  std::mt19937_64 rng(static_cast<std::uint64_t>(o.seed));
  std::uniform_real_distribution<double> target(o.target_min_v, o.target_max_v), rate(o.rate_min_v_per_s, o.rate_max_v_per_s);
  std::vector<std::pair<double, double>> plan;  // (goal V, rate V/s)
  for (int i = 0; i < o.moves; ++i) {
    const double g = target(rng);
    plan.emplace_back(g, rate(rng));
  }
  std::vector<DemoStep> s;
  double v = 0.0;
  for (int rep = 0; rep < 3; ++rep) {  // the warm-up, then the scored passes with the tracking trim off and on
    const int mode = rep == 2 ? 1 : 0;
    const bool warmup = rep == 0;
    for (int i = 0; i < o.moves; ++i)
      move_and_hold(s, mode, i, warmup, v, plan[i].first, plan[i].second, o.hold_s, "hold", hz);
    move_and_hold(s, mode, o.moves, warmup, v, 0.0, 1.0, o.rest_s, "rest", hz);
  }
  return s;
}

std::vector<DemoRun::MoveScore> DemoRun::move_scores() const {
  std::vector<MoveScore> out(2);
  for (const auto& r : rows_) {
    if (r.step.phase == "warmup") continue;
    MoveScore& m = out[r.step.mode ? 1 : 0];
    m.applied_min_v = std::min(m.applied_min_v, r.applied_v);
    m.applied_max_v = std::max(m.applied_max_v, r.applied_v);
    const double e = std::abs(r.true_nm - r.ideal_nm);
    if (moves_scored_as_move(r.step, moves_.settle_s)) {
      m.move_max_nm = std::max(m.move_max_nm, e), m.move_mean_nm += e, ++m.move_samples;
    } else if (r.step.phase == "hold" && r.step.held_s >= moves_.hold_score_from_s) {
      m.hold_max_nm = std::max(m.hold_max_nm, e), m.hold_mean_nm += e, ++m.hold_samples;
    }
    if (const Estimate* est = estimate_at(r.stamp_s); est && est->tracking_trim_state == "active")
      ++m.tracking_active_samples;
  }
  for (auto& m : out) {
    m.move_mean_nm /= std::max<std::size_t>(1, m.move_samples);
    m.hold_mean_nm /= std::max<std::size_t>(1, m.hold_samples);
  }
  return out;
}

// The tracking-trim scenario: moves and holds, the tracking trim off against on (the hold trim on in both).
void DemoRun::write_tracking_trim_json(std::ostream& js) const {
  const auto m = move_scores();
  js << "{\"lockstep\": " << (lockstep_ ? "true" : "false") << ", \"scenario\": \"tracking_trim\""
     << ", \"moves\": " << moves_.moves << ", \"moves_seed\": " << moves_.seed << ", \"hold_s\": " << moves_.hold_s
     << ", \"settle_s\": " << moves_.settle_s << ", \"hold_score_from_s\": " << moves_.hold_score_from_s;
  for (int k = 0; k < 2; ++k) {
    const std::string p = k ? "\"tracking_on_" : "\"tracking_off_";
    js << ", " << p << "move_max_nm\": " << m[k].move_max_nm << ", " << p << "move_mean_nm\": " << m[k].move_mean_nm
       << ", " << p << "hold_max_nm\": " << m[k].hold_max_nm << ", " << p << "hold_mean_nm\": " << m[k].hold_mean_nm
       << ", " << p << "move_samples\": " << m[k].move_samples << ", " << p << "hold_samples\": " << m[k].hold_samples
       << ", " << p << "active_samples\": " << m[k].tracking_active_samples << ", " << p << "applied_min_v\": "
       << m[k].applied_min_v << ", " << p << "applied_max_v\": " << m[k].applied_max_v;
  }
  js << "}\n";
}

}  // namespace piezo::compensation

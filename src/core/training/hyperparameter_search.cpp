#include "piezo_compensation/training/hyperparameter_search.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <numeric>
#include <random>
#include <sstream>
#include <stdexcept>

namespace piezo::training {

namespace {

constexpr double kPi = 3.14159265358979323846;

double uniform01(std::mt19937_64& rng) { return static_cast<double>(rng() >> 11) * 0x1.0p-53; }

double normal(std::mt19937_64& rng) {
  // Box–Muller from our own uniforms: identical across standard libraries.
  const double u1 = std::max(uniform01(rng), 1e-300), u2 = uniform01(rng);
  return std::sqrt(-2.0 * std::log(u1)) * std::cos(2.0 * kPi * u2);
}

bool is_numeric(const ParamDef& p) { return p.type != ParamDef::Type::Categorical; }

// Search happens in an internal coordinate: log10 for LogFloat, the value otherwise (ints widened by ±0.5
// so every integer has equal mass).
double internal_low(const ParamDef& p) {
  if (p.type == ParamDef::Type::LogFloat) return std::log10(p.low);
  if (p.type == ParamDef::Type::Int) return p.low - 0.5;
  return p.low;
}
double internal_high(const ParamDef& p) {
  if (p.type == ParamDef::Type::LogFloat) return std::log10(p.high);
  if (p.type == ParamDef::Type::Int) return p.high + 0.5;
  return p.high;
}
double to_internal(const ParamDef& p, double v) { return p.type == ParamDef::Type::LogFloat ? std::log10(v) : v; }
double from_internal(const ParamDef& p, double u) {
  u = std::clamp(u, internal_low(p), internal_high(p));
  if (p.type == ParamDef::Type::LogFloat) return std::pow(10.0, u);
  if (p.type == ParamDef::Type::Int) return std::clamp(std::round(u), p.low, p.high);
  return u;
}

// Parzen estimator: a truncated Gaussian per observation plus a uniform prior component.
struct Parzen {
  std::vector<double> mu, sigma;
  double lo = 0, hi = 1;

  Parzen(std::vector<double> points, double low, double high) : lo(low), hi(high) {
    std::sort(points.begin(), points.end());
    const double range = hi - lo;
    const std::size_t n = points.size();
    for (std::size_t i = 0; i < n; ++i) {
      // Bandwidth from the neighbours (Optuna's rule), clipped to a sensible range.
      const double left = i > 0 ? points[i] - points[i - 1] : points[i] - lo;
      const double right = i + 1 < n ? points[i + 1] - points[i] : hi - points[i];
      double s = std::max(left, right);
      s = std::clamp(s, range / std::min(100.0, 1.0 + static_cast<double>(n)), range);
      mu.push_back(points[i]);
      sigma.push_back(s);
    }
  }

  double pdf(double x) const {
    const double range = hi - lo;
    const double w = 1.0 / static_cast<double>(mu.size() + 1);
    double p = w / range;  // prior
    for (std::size_t i = 0; i < mu.size(); ++i) {
      const double z = (x - mu[i]) / sigma[i];
      const double mass = 0.5 * (std::erf((hi - mu[i]) / (sigma[i] * std::sqrt(2.0))) -
                                 std::erf((lo - mu[i]) / (sigma[i] * std::sqrt(2.0))));
      p += w * std::exp(-0.5 * z * z) / (sigma[i] * std::sqrt(2.0 * kPi) * std::max(mass, 1e-12));
    }
    return p;
  }

  double sample(std::mt19937_64& rng) const {
    const std::size_t k = rng() % (mu.size() + 1);
    if (k == mu.size()) return lo + (hi - lo) * uniform01(rng);
    for (int tries = 0; tries < 100; ++tries) {
      const double x = mu[k] + sigma[k] * normal(rng);
      if (x >= lo && x <= hi) return x;
    }
    return std::clamp(mu[k], lo, hi);
  }
};

TrialParams random_params(const std::vector<ParamDef>& space, std::mt19937_64& rng) {
  TrialParams t;
  for (const auto& p : space) {
    if (is_numeric(p)) {
      const double u = internal_low(p) + (internal_high(p) - internal_low(p)) * uniform01(rng);
      t.number[p.name] = from_internal(p, u);
    } else {
      t.choice[p.name] = p.choices[rng() % p.choices.size()];
    }
  }
  return t;
}

TrialParams tpe_params(const std::vector<ParamDef>& space, const std::vector<TrialRecord>& history,
                       const SearchConfig& config, std::mt19937_64& rng) {
  std::vector<std::size_t> order(history.size());
  std::iota(order.begin(), order.end(), std::size_t{0});
  std::stable_sort(order.begin(), order.end(),
                   [&](std::size_t a, std::size_t b) { return history[a].value < history[b].value; });
  const std::size_t n_good = std::max<std::size_t>(
      1, static_cast<std::size_t>(std::ceil(config.gamma * static_cast<double>(history.size()))));
  TrialParams t;
  for (const auto& p : space) {
    if (is_numeric(p)) {
      std::vector<double> good, bad;
      for (std::size_t r = 0; r < order.size(); ++r)
        (r < n_good ? good : bad).push_back(to_internal(p, history[order[r]].params.number.at(p.name)));
      const Parzen l(good, internal_low(p), internal_high(p));
      const Parzen g(bad, internal_low(p), internal_high(p));
      double best_x = l.sample(rng), best_score = -std::numeric_limits<double>::infinity();
      for (int c = 0; c < config.candidates; ++c) {
        const double x = c == 0 ? best_x : l.sample(rng);
        const double score = std::log(l.pdf(x)) - std::log(g.pdf(x));
        if (score > best_score) {
          best_score = score;
          best_x = x;
        }
      }
      t.number[p.name] = from_internal(p, best_x);
    } else {
      // Categorical: smoothed counts in the good and bad groups; pick the best ratio among sampled candidates.
      const std::size_t k = p.choices.size();
      std::vector<double> lg(k, 1.0), lb(k, 1.0);
      for (std::size_t r = 0; r < order.size(); ++r) {
        const std::string& c = history[order[r]].params.choice.at(p.name);
        const auto idx = static_cast<std::size_t>(std::find(p.choices.begin(), p.choices.end(), c) - p.choices.begin());
        if (idx < k) (r < n_good ? lg : lb)[idx] += 1.0;
      }
      const double sg = std::accumulate(lg.begin(), lg.end(), 0.0), sb = std::accumulate(lb.begin(), lb.end(), 0.0);
      std::size_t best_i = 0;
      double best_score = -std::numeric_limits<double>::infinity();
      for (int c = 0; c < config.candidates; ++c) {
        double u = uniform01(rng) * sg;
        std::size_t i = 0;
        while (i + 1 < k && u >= lg[i]) u -= lg[i++];
        const double score = std::log(lg[i] / sg) - std::log(lb[i] / sb);
        if (score > best_score) {
          best_score = score;
          best_i = i;
        }
      }
      t.choice[p.name] = p.choices[best_i];
    }
  }
  return t;
}

}  // namespace

std::string TrialParams::to_string() const {
  std::ostringstream os;
  bool first = true;
  for (const auto& [k, v] : number) {
    os << (first ? "" : " ") << k << "=" << v;
    first = false;
  }
  for (const auto& [k, v] : choice) {
    os << (first ? "" : " ") << k << "=" << v;
    first = false;
  }
  return os.str();
}

SearchResult tpe_search(const std::vector<ParamDef>& space, const SearchConfig& config, const TrialObjective& objective) {
  if (config.trials < 1) throw std::runtime_error("hyperparameter search: trials must be at least 1");
  for (const auto& p : space) {
    if (p.type == ParamDef::Type::Categorical && p.choices.empty())
      throw std::runtime_error("hyperparameter search: '" + p.name + "' has no choices");
    if (is_numeric(p) && !(p.high >= p.low))
      throw std::runtime_error("hyperparameter search: '" + p.name + "' has high < low");
    if (p.type == ParamDef::Type::LogFloat && !(p.low > 0.0))
      throw std::runtime_error("hyperparameter search: log parameter '" + p.name + "' needs low > 0");
  }
  const auto t0 = std::chrono::steady_clock::now();
  auto elapsed = [&] { return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count(); };
  std::mt19937_64 rng(config.seed);
  SearchResult result;
  for (int trial = 0; trial < config.trials; ++trial) {
    const double left = config.time_budget_s > 0.0 ? config.time_budget_s - elapsed()
                                                   : std::numeric_limits<double>::infinity();
    if (trial > 0 && left <= 0.0) break;
    TrialRecord rec;
    rec.params = trial < config.startup_trials ? random_params(space, rng) : tpe_params(space, result.trials, config, rng);
    const double start = elapsed();
    try {
      rec.value = objective(rec.params, trial, left);
    } catch (const std::exception&) {
      rec.value = std::numeric_limits<double>::infinity();
    }
    if (!std::isfinite(rec.value)) rec.value = std::numeric_limits<double>::infinity();
    rec.seconds = elapsed() - start;
    result.trials.push_back(rec);
    if (rec.value < result.trials[result.best].value) result.best = result.trials.size() - 1;
    if (config.progress) config.progress(trial + 1, config.trials, "trial");
  }
  return result;
}

namespace {
ParamDef int_param(const std::string& n, double lo, double hi) { return {n, ParamDef::Type::Int, lo, hi, {}}; }
ParamDef optimizer_param() { return {"optimizer", ParamDef::Type::Categorical, 0, 0, {"adam", "rmsprop", "sgd"}}; }
ParamDef lr_param() { return {"learning_rate", ParamDef::Type::LogFloat, 1e-5, 1e-1, {}}; }
}  // namespace

std::vector<ParamDef> dense_search_space() {
  return {int_param("depth", 1, 5), int_param("width", 1, 20), optimizer_param(), lr_param()};
}
std::vector<ParamDef> lstm_search_space() {
  return {int_param("layers", 1, 5), int_param("hidden", 4, 64), optimizer_param(), lr_param()};
}
std::vector<ParamDef> kan_search_space() {
  return {int_param("width", 1, 10), int_param("grid", 3, 20), int_param("order", 1, 4), lr_param()};
}

}  // namespace piezo::training

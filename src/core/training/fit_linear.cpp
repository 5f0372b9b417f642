// Fitting of kind "linear" (moved from models/linear_model.cpp; the model itself stays in models/).
#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "piezo_compensation/models/linear_model.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/training/fit_common.h"
#include "piezo_compensation/training/fitters.h"
#include "piezo_compensation/training/lasso.h"

namespace piezo::training {

using namespace models;  // the fit code names the model's classes as models/ does

namespace {

std::unique_ptr<LinearModel> fit_linear_on(const features::FeatureSpec& spec, const FitRequest& req,
                                           const std::string& method) {
  const int folds = method == "lasso" ? std::max(2, option_int(req.options, "folds", 5)) : 1;
  const auto blocks = block_gram(spec, *req.train, req.axis, folds, req.progress);
  GramStats all = blocks[0];
  for (std::size_t k = 1; k < blocks.size(); ++k) all += blocks[k];
  Eigen::VectorXd beta;
  if (method == "lasso") {
    LassoOptions lo;
    lo.folds = folds;
    const LassoPath path = lasso_path_cv(blocks, lo, req.progress);
    const std::string choice = option_str(req.options, "lasso_choice", "1se");
    if (choice != "1se" && choice != "min") throw std::runtime_error("option 'lasso_choice': expected 1se or min");
    beta = path.coefs[choice == "min" ? path.index_min : path.index_1se];
  } else {
    // OLS keeps a negligible ridge (relative 1e-10) so exactly collinear candidates stay solvable.
    const Eigen::MatrixXd G = all.centered_xx();
    const double rel = method == "ridge" ? option_num(req.options, "ridge_lambda", 1e-3) : 1e-10;
    beta = solve_normal(G, all.centered_xy(), rel * all.n);
  }
  const double b = all.mean_y() - all.mean_x().dot(beta);
  return std::make_unique<LinearModel>(spec, req.train->sample_rate_hz(), beta, b, method);
}

}  // namespace

double free_run_gain(const models::Model& model, const io::Dataset& data, const std::string& axis) {
  if (!model.uses_position_history() || data.empty()) return 0.0;
  const io::AxisSeries& ax = data.axis(axis);
  constexpr double kDelta = 1000.0;  // nm; the model is linear in its start, so any size gives the same ratio
  ModelPtr a = model.clone(), b = model.clone();
  a->reset(ax.voltage_v[0], ax.position_nm[0]);
  b->reset(ax.voltage_v[0], ax.position_nm[0] + kDelta);
  StreamOptions so;
  so.reset = false;
  so.keep_diverging = true;
  const std::vector<double> pa = stream_model(*a, data, axis, so).prediction, pb = stream_model(*b, data, axis, so).prediction;
  double gain = 0.0;
  for (std::size_t i = 0; i < pa.size(); ++i) {
    const double g = std::abs(pb[i] - pa[i]) / kDelta;
    gain = std::isfinite(g) ? std::max(gain, g) : INFINITY;
  }
  return gain;
}

models::ModelPtr fit_linear(const FitRequest& req) {
  using namespace training;
  if (!req.train) throw std::runtime_error("linear fit: no training data");
  const std::string method = option_str(req.options, "method", "ols");
  if (method != "ols" && method != "ridge" && method != "lasso")
    throw std::runtime_error("option 'method': expected ols, ridge or lasso, got '" + method + "'");
  const features::FeatureSpec spec = resolve_features(req, "study");
  std::unique_ptr<LinearModel> m = fit_linear_on(spec, req, method);
  // Features that read the model's own past positions run back on themselves in free run; where that recursion
  // amplifies a start error (two free runs over the training data started 1 µm apart drift more than
  // kMaxFreeRunGain µm apart) the model is numerically wild whatever its score: refit on the voltage features.
  const double gain = free_run_gain(*m, *req.train, req.axis);
  if (gain > kMaxFreeRunGain) {
    features::FeatureSpec voltage_only;
    for (const auto& f : spec.features)
      if (!f.reads_position()) voltage_only.features.push_back(f);
    if (voltage_only.features.empty())
      throw std::runtime_error("linear fit: its position features amplify a start error " + std::to_string(gain) +
                               "x in free run and it has no other features");
    if (req.progress)
      req.progress(0, 0, "linear: position features amplify a start error " + std::to_string(gain) +
                             "x in free run; refitted on the voltage features");
    m = fit_linear_on(fit_standardisation(voltage_only, *req.train, req.axis), req, method);
  }
  m->meta = make_meta(req);
  return m;
}

}  // namespace piezo::training

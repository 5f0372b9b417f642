// Fitting of kind "linear" (moved from models/linear_model.cpp; the model itself stays in models/).
#include <cmath>
#include <stdexcept>

#include "piezo_compensation/models/linear_model.h"
#include "piezo_compensation/training/fit_common.h"
#include "piezo_compensation/training/fitters.h"
#include "piezo_compensation/training/lasso.h"

namespace piezo::training {

using namespace models;  // the fit code names the model's classes as models/ does

models::ModelPtr fit_linear(const FitRequest& req) {
  using namespace training;
  if (!req.train) throw std::runtime_error("linear fit: no training data");
  const std::string method = option_str(req.options, "method", "ols");
  if (method != "ols" && method != "ridge" && method != "lasso")
    throw std::runtime_error("option 'method': expected ols, ridge or lasso, got '" + method + "'");
  const features::FeatureSpec spec = resolve_features(req, "study");
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
  auto m = std::make_unique<LinearModel>(spec, req.train->sample_rate_hz(), beta, b, method);
  m->meta = make_meta(req);
  return m;
}

}  // namespace piezo::training

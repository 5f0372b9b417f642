// Fitting of kind "dense" (moved from models/dense_model.cpp; the model itself stays in models/).
#include <algorithm>
#include <cmath>
#include <random>
#include <sstream>
#include <stdexcept>

#include "piezo_compensation/models/dense_model.h"
#include "piezo_compensation/training/fit_common.h"
#include "piezo_compensation/training/fitters.h"
#include "piezo_compensation/training/hyperparameter_search.h"

namespace piezo::training {

using namespace models;  // the fit code names the model's classes as models/ does

using DenseObjective = ColumnObjective<DenseNet>;

namespace {

using DenseTrial = NeuralTrial<DenseModel>;

// Starts the network at the least-squares linear fit of the features: hidden unit 0 of the first layer carries
// β·x + K (K keeps it in the linear part on every training sample), unit 0 of each further layer passes it on,
// the output reads it with weight 1 and the others with 0; every other weight keeps its He draw. Trained from
// there, the network adds the non-linear part instead of rebuilding the linear one: with the study's plain He
// start, 800 Adam steps left a 1 × 10 network at 5–9 % of range where this start gives < 1 % (stage matrix).
Eigen::VectorXd linear_start(const DenseNet& net, std::uint64_t seed, const Eigen::MatrixXd& x, const Eigen::VectorXd& y) {
  const DenseShape& s = net.shape();
  Eigen::VectorXd p = net.initial_params(seed);
  const Eigen::Index n_in = x.rows();
  const ColumnLinearFit fit = linear_fit_columns(x, y);
  const Eigen::VectorXd lin = fit.beta.transpose() * x;
  const double k = s.depth > 0 ? std::max(0.0, -lin.minCoeff()) + 1.0 : 0.0;
  Eigen::Index o = 0;
  int in = static_cast<int>(n_in);
  for (int l = 0; l <= s.depth; ++l) {
    const int out = l < s.depth ? s.width : 1;
    for (int i = 0; i < in; ++i) p[o + i * out] = l == 0 ? fit.beta[i] : (i == 0 ? 1.0 : 0.0);  // row 0 of W
    o += static_cast<Eigen::Index>(in) * out;
    p[o] = (l == 0 ? k : 0.0) + (l == s.depth ? fit.intercept - k : 0.0);  // bias of unit 0
    o += out;
    in = out;
  }
  return p;
}

DenseTrial train_dense(const training::PreparedData& data, const DenseShape& shape, training::TrainerConfig cfg,
                       bool linear_init) {
  const DenseNet net(shape);
  const DenseObjective train_obj(net, data.x_train, data.y_train);
  const DenseObjective val_obj(net, data.x_validation, data.y_validation);
  const Eigen::VectorXd init =
      linear_init ? linear_start(net, cfg.seed, data.x_train, data.y_train) : net.initial_params(cfg.seed);
  const training::TrainResult r = training::train(train_obj, &val_obj, init, cfg);
  return make_trial(std::make_unique<DenseModel>(data.spec, data.sample_rate_hz, shape, r.params, data.target), cfg, r,
                    data.target.scale_nm, "batch_size");
}

}  // namespace

std::unique_ptr<models::DenseModel> fit_dense(const FitRequest& request) {
  const training::PreparedData data = training::prepare_data(request, "dense", {"depth", "width", "leaky_slope", "init"});
  DenseShape shape;
  shape.inputs = static_cast<int>(data.spec.size());
  shape.depth = training::option_int(request.options, "depth", 1);
  shape.width = training::option_int(request.options, "width", 10);
  shape.leaky_slope = training::option_num(request.options, "leaky_slope", 0.01);
  const bool linear_init = neural_linear_init(request.options);
  training::TrainerConfig cfg = training::trainer_config(request, 50, 256);
  return fit_or_tune(
      "dense", training::dense_search_space(), request, cfg,
      [&](training::TrainerConfig c) { return train_dense(data, shape, c, linear_init); },
      [&](const training::TrialParams& p, training::TrainerConfig c) {
        DenseShape s = shape;
        s.depth = static_cast<int>(p.number.at("depth"));
        s.width = static_cast<int>(p.number.at("width"));
        return train_dense(data, s, with_trial_optimizer(c, p), linear_init);
      });
}

}  // namespace piezo::training

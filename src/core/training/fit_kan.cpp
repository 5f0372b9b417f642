// Fitting of kind "kan" (moved from models/kan_model.cpp; the model itself stays in models/).
#include <cmath>
#include <random>
#include <sstream>
#include <stdexcept>

#include "piezo_compensation/models/kan_model.h"
#include "piezo_compensation/training/fit_common.h"
#include "piezo_compensation/training/fitters.h"
#include "piezo_compensation/training/hyperparameter_search.h"

namespace piezo::training {

using namespace models;  // the fit code names the model's classes as models/ does

using KanObjective = ColumnObjective<KanNet>;

namespace {

using KanTrial = NeuralTrial<KanModel>;

// Sets edge input→output of `layer` to a·x (the B-splines reproduce a line with their Greville abscissae as
// coefficients, on the grid's span), no SiLU part.
void set_linear_edge(const KanNet& net, Eigen::VectorXd& p, int layer, int input, int output, double a) {
  const Eigen::Index e = net.edge_offset(layer, input, output);
  const double* t = net.knots(layer, input);
  const int d = net.shape().order;
  p[e] = 0.0;
  for (int k = 0; k < net.num_basis(); ++k) {
    double xi = 0.0;
    for (int r = 1; r <= d; ++r) xi += t[k + r];
    p[e + 1 + k] = a * (d > 0 ? xi / d : t[k]);
  }
}

// Starts the network at the least-squares linear fit of the features (the dense kind's linear start, see
// fit_dense.cpp): node 0 of the first hidden layer sums β_i·x_i, node 0 of each further layer passes it on,
// every other edge into the output is zero; the other edges keep their random draws. The grids are placed on
// the data before and after, so the lines hold over the training range.
void kan_linear_start(KanNet& net, Eigen::VectorXd& p, const Eigen::MatrixXd& x, const Eigen::VectorXd& y) {
  const ColumnLinearFit fit = linear_fit_columns(x, y);
  const Eigen::VectorXd& beta = fit.beta;
  const std::vector<int>& w = net.shape().widths;
  for (int i = 0; i < w[0]; ++i) set_linear_edge(net, p, 0, i, 0, beta[i]);
  p[net.bias_offset(0)] = net.num_layers() == 1 ? fit.intercept : 0.0;
  for (int l = 1; l < net.num_layers(); ++l) {
    net.update_grids(p, x);  // layer l's grid onto node 0's new range (the functions stay)
    const bool last = l + 1 == net.num_layers();
    set_linear_edge(net, p, l, 0, 0, 1.0);
    for (int i = 1; i < w[static_cast<std::size_t>(l)]; ++i)
      p.segment(net.edge_offset(l, i, 0), 1 + net.num_basis()).setZero();
    p[net.bias_offset(l)] = last ? fit.intercept : 0.0;
  }
  net.update_grids(p, x);
}

KanTrial train_kan(const training::PreparedData& data, const KanShape& shape, int grid_updates,
                   training::TrainerConfig cfg, bool linear_init) {
  KanNet net(shape);
  Eigen::VectorXd init = net.initial_params(cfg.seed);
  net.update_grids(init, data.x_train);
  if (linear_init) kan_linear_start(net, init, data.x_train, data.y_train);
  const KanObjective train_obj(net, data.x_train, data.y_train);
  const KanObjective val_obj(net, data.x_validation, data.y_validation);
  // The objectives read the grids through `net`, so updating them in the hook is seen by later batches.
  cfg.on_epoch_end = [&](Eigen::VectorXd& params, int epoch) {
    if (epoch > grid_updates) return false;
    net.update_grids(params, data.x_train);
    return true;
  };
  const training::TrainResult r = training::train(train_obj, &val_obj, init, cfg);
  return make_trial(std::make_unique<KanModel>(data.spec, data.sample_rate_hz, net, r.params, data.target), cfg, r,
                    data.target.scale_nm, "batch_size", {{"grid_updates", YAML::Node(grid_updates)}});
}

}  // namespace

std::unique_ptr<models::KanModel> fit_kan(const FitRequest& request) {
  const training::PreparedData data = training::prepare_data(request, "kan", {"width", "hidden_layers", "grid", "order", "grid_updates", "init"});
  if (data.spec.size() > static_cast<std::size_t>(models::KanNet::kMaxWidth))
    throw std::runtime_error("kan: " + std::to_string(data.spec.size()) + " input features, at most " +
                             std::to_string(models::KanNet::kMaxWidth) +
                             " (option 'features': a smaller set, e.g. voltage_history)");
  const int width = training::option_int(request.options, "width", 4);
  const int hidden_layers = training::option_int(request.options, "hidden_layers", 1);
  if (hidden_layers < 0 || hidden_layers > 4) throw std::runtime_error("option 'hidden_layers' must be in 0..4");
  auto shape_for = [&](int w, int grid, int order) {
    KanShape s;
    s.widths = {static_cast<int>(data.spec.size())};
    for (int l = 0; l < hidden_layers; ++l) s.widths.push_back(w);
    s.widths.push_back(1);
    s.grid = grid;
    s.order = order;
    return s;
  };
  const KanShape shape = shape_for(width, training::option_int(request.options, "grid", 5),
                                   training::option_int(request.options, "order", 3));
  const int grid_updates = training::option_int(request.options, "grid_updates", 3);
  const bool linear_init = neural_linear_init(request.options);
  training::TrainerConfig cfg = training::trainer_config(request, 50, 256);
  if (!request.options || !request.options["learning_rate"]) cfg.optimizer.learning_rate = 3e-3;
  auto m = fit_or_tune(
      "kan", training::kan_search_space(), request, cfg,
      [&](training::TrainerConfig c) { return train_kan(data, shape, grid_updates, c, linear_init); },
      [&](const training::TrialParams& p, training::TrainerConfig c) {
        const KanShape s = shape_for(static_cast<int>(p.number.at("width")), static_cast<int>(p.number.at("grid")),
                                     static_cast<int>(p.number.at("order")));
        return train_kan(data, s, grid_updates, with_trial_optimizer(c, p), linear_init);
      });
  // The interpretable form travels with the model file (one line per edge).
  YAML::Node lines(YAML::NodeType::Sequence);
  std::istringstream text(m->formulas());
  for (std::string line; std::getline(text, line);)
    if (line.find_first_not_of(' ') != std::string::npos) lines.push_back(line.substr(line.find_first_not_of(' ')));
  m->training_info["formulas"] = lines;
  return m;
}

}  // namespace piezo::training

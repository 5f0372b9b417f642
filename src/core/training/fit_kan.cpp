// Fitting of kind "kan" (moved from models/kan_model.cpp; the model itself stays in models/).
#include <cmath>
#include <random>
#include <sstream>
#include <stdexcept>

#include "piezo_compensation/models/kan_model.h"
#include "piezo_compensation/training/fitters.h"
#include "piezo_compensation/training/hyperparameter_search.h"

namespace piezo::training {

using namespace models;  // the fit code names the model's classes as models/ does

using KanObjective = ColumnObjective<KanNet>;

namespace {

using KanTrial = NeuralTrial<KanModel>;

KanTrial train_kan(const training::PreparedData& data, const KanShape& shape, int grid_updates,
                   training::TrainerConfig cfg) {
  KanNet net(shape);
  Eigen::VectorXd init = net.initial_params(cfg.seed);
  net.update_grids(init, data.x_train);
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
  const training::PreparedData data = training::prepare_data(request, "kan", {"width", "hidden_layers", "grid", "order", "grid_updates"});
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
  training::TrainerConfig cfg = training::trainer_config(request, 50, 256);
  if (!request.options || !request.options["learning_rate"]) cfg.optimizer.learning_rate = 3e-3;
  auto m = fit_or_tune(
      "kan", training::kan_search_space(), request, cfg,
      [&](training::TrainerConfig c) { return train_kan(data, shape, grid_updates, c); },
      [&](const training::TrialParams& p, training::TrainerConfig c) {
        const KanShape s = shape_for(static_cast<int>(p.number.at("width")), static_cast<int>(p.number.at("grid")),
                                     static_cast<int>(p.number.at("order")));
        return train_kan(data, s, grid_updates, with_trial_optimizer(c, p));
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

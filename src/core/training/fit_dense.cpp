// Fitting of kind "dense" (moved from models/dense_model.cpp; the model itself stays in models/).
#include <cmath>
#include <random>
#include <sstream>
#include <stdexcept>

#include "piezo_compensation/models/dense_model.h"
#include "piezo_compensation/training/fitters.h"
#include "piezo_compensation/training/hyperparameter_search.h"

namespace piezo::training {

using namespace models;  // the fit code names the model's classes as models/ does

using DenseObjective = ColumnObjective<DenseNet>;

namespace {

using DenseTrial = NeuralTrial<DenseModel>;

DenseTrial train_dense(const training::PreparedData& data, const DenseShape& shape, training::TrainerConfig cfg) {
  const DenseNet net(shape);
  const DenseObjective train_obj(net, data.x_train, data.y_train);
  const DenseObjective val_obj(net, data.x_validation, data.y_validation);
  const training::TrainResult r = training::train(train_obj, &val_obj, net.initial_params(cfg.seed), cfg);
  return make_trial(std::make_unique<DenseModel>(data.spec, data.sample_rate_hz, shape, r.params, data.target), cfg, r,
                    data.target.scale_nm, "batch_size");
}

}  // namespace

std::unique_ptr<models::DenseModel> fit_dense(const FitRequest& request) {
  const training::PreparedData data = training::prepare_data(request, "dense", {"depth", "width", "leaky_slope"});
  DenseShape shape;
  shape.inputs = static_cast<int>(data.spec.size());
  shape.depth = training::option_int(request.options, "depth", 1);
  shape.width = training::option_int(request.options, "width", 10);
  shape.leaky_slope = training::option_num(request.options, "leaky_slope", 0.01);
  training::TrainerConfig cfg = training::trainer_config(request, 50, 256);
  return fit_or_tune(
      "dense", training::dense_search_space(), request, cfg,
      [&](training::TrainerConfig c) { return train_dense(data, shape, c); },
      [&](const training::TrialParams& p, training::TrainerConfig c) {
        DenseShape s = shape;
        s.depth = static_cast<int>(p.number.at("depth"));
        s.width = static_cast<int>(p.number.at("width"));
        return train_dense(data, s, with_trial_optimizer(c, p));
      });
}

}  // namespace piezo::training

// Activation functions shared by the neural kinds (LSTM gates, KAN SiLU edges).
#pragma once

#include <cmath>

namespace piezo::models {

inline double sigmoid(double z) { return 1.0 / (1.0 + std::exp(-z)); }

}  // namespace piezo::models

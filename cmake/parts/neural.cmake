# Neural models (dense, LSTM, KAN), optimisers, trainer and hyperparameter search (issue 5, second half).
piezo_unit_test(test_models_dense test/unit/test_models_dense.cpp)
piezo_unit_test(test_models_lstm test/unit/test_models_lstm.cpp)
piezo_unit_test(test_models_kan test/unit/test_models_kan.cpp)
piezo_unit_test(test_training_optimizers test/unit/test_training_optimizers.cpp)

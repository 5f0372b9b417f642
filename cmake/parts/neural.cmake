# Neural models (dense, LSTM, KAN), optimisers, trainer and hyperparameter search.
piezo_unit_test(test_models_dense test/unit/test_models_dense.cpp)
piezo_unit_test(test_models_lstm test/unit/test_models_lstm.cpp)
piezo_unit_test(test_models_kan test/unit/test_models_kan.cpp)
piezo_unit_test(test_training_optimizers test/unit/test_training_optimizers.cpp)
if(CATKIN_ENABLE_TESTING)
  # The exported C99 headers are compiled and run against the C++ models.
  target_compile_definitions(test_models_dense PRIVATE PIEZO_C_COMPILER="${CMAKE_C_COMPILER}")
  target_compile_definitions(test_models_lstm PRIVATE PIEZO_C_COMPILER="${CMAKE_C_COMPILER}")
  target_compile_definitions(test_models_kan PRIVATE PIEZO_C_COMPILER="${CMAKE_C_COMPILER}")
endif()
piezo_benchmark(bench_models_neural bench/bench_models_neural.cpp)
# Its training data comes from the tests' generator (test/unit/hysteretic_walk.h).
target_include_directories(bench_models_neural PRIVATE ${CMAKE_CURRENT_SOURCE_DIR}/test/unit)
if(CATKIN_ENABLE_TESTING)
  # The smoke run trains on a small synthetic set; `scripts/piezo bench` uses the full 26 h (~1 M samples).
  set_tests_properties(bench_models_neural_smoke PROPERTIES ENVIRONMENT "PIEZO_BENCH_TRAIN_SAMPLES=3000")
endif()

# features/, models/ (linear, PI, creep, model file, C export), training/ (lasso, fit_common),
# analysis/evaluation/ (eval).
piezo_unit_test(test_features_stream test/unit/test_features_stream.cpp)
piezo_unit_test(test_lasso test/unit/test_lasso.cpp)
piezo_unit_test(test_models_linear test/unit/test_models_linear.cpp)
piezo_unit_test(test_models_pi test/unit/test_models_pi.cpp)
piezo_unit_test(test_models_creep test/unit/test_models_creep.cpp)
piezo_unit_test(test_models_prony test/unit/test_models_prony.cpp)
piezo_unit_test(test_models_pi_creep_play test/unit/test_models_pi_creep_play.cpp)
# Models at the data's rate (Model::set_step_s): another rate, a jittered clock, the refusal of a fixed-rate kind.
piezo_unit_test(test_models_step test/unit/test_models_step.cpp)
# Every registered kind: fit, model-file round trip, clone/stream equality, C export, the rate contract.
piezo_unit_test(test_models_conformance test/unit/test_models_conformance.cpp)
# The creep-protocol fits of the preisach kind and of the PI kind it is compared with, side by side.
piezo_unit_test_shards(test_models_preisach test/unit/test_models_preisach.cpp SHARDS
  preisach "-Preisach.PiCreepCannotFollowThePreisachLoops" pi "Preisach.PiCreepCannotFollowThePreisachLoops")
piezo_unit_test(test_models_file test/unit/test_models_file.cpp)
piezo_unit_test(test_input_roundtrip test/unit/test_input_roundtrip.cpp)
piezo_unit_test(test_models_export test/unit/test_models_export.cpp)
# The tests that compile a model's C export and run it need the C compiler.
foreach(t test_models_pi_creep_play test_models_conformance test_models_export)
  if(TARGET ${t})
    target_compile_definitions(${t} PRIVATE PIEZO_C_COMPILER="${CMAKE_C_COMPILER}")
  endif()
endforeach()
piezo_unit_test(test_eval_metrics test/unit/test_eval_metrics.cpp)
# The fit plan the CLI runs (training/fit_plan.h).
piezo_unit_test(test_training_fit_plan test/unit/test_training_fit_plan.cpp)
# The start-up state estimate (models/start_state.h): the checks (fast) and the docs/models.md table (slow: fits).
piezo_unit_test_shards(test_start_state test/unit/test_start_state.cpp SHARDS
  checks "StartState.*" table "StartStateTable.*")
piezo_benchmark(bench_models_linear bench/bench_models_linear.cpp)

piezo_slow_tests(test_models_step test_models_conformance test_start_state_table test_models_creep test_models_prony test_models_preisach_preisach test_models_preisach_pi)

# analysis/residual/: the residual loop, its augmented model kind, tests.
piezo_unit_test(test_residual_stats test/unit/test_residual_stats.cpp)
piezo_unit_test(test_residual_acceptance test/unit/test_residual_acceptance.cpp)
piezo_unit_test(test_residual_validation test/unit/test_residual_validation.cpp)
piezo_unit_test(test_residual_augmented test/unit/test_residual_augmented.cpp)
piezo_unit_test(test_residual_loop test/unit/test_residual_loop.cpp)
piezo_unit_test(test_residual_loop_signals test/unit/test_residual_loop_signals.cpp)
piezo_unit_test(test_residual_loop_coupling test/unit/test_residual_loop_coupling.cpp)
# The simulator and gain runs are split over several files so each stays under the unit-test time rule.
piezo_unit_test(test_residual_sim test/unit/test_residual_sim.cpp)
piezo_unit_test(test_residual_sim_clean test/unit/test_residual_sim_clean.cpp)
piezo_unit_test(test_residual_sim_coupling test/unit/test_residual_sim_coupling.cpp)
piezo_unit_test(test_residual_sim_periodic test/unit/test_residual_sim_periodic.cpp)
piezo_unit_test(test_residual_sim_disturbance test/unit/test_residual_sim_disturbance.cpp)
piezo_unit_test(test_residual_gain test/unit/test_residual_gain.cpp)
piezo_unit_test(test_residual_gain_drift test/unit/test_residual_gain_drift.cpp)
piezo_unit_test(test_residual_gain_temperature test/unit/test_residual_gain_temperature.cpp)
piezo_unit_test(test_residual_gain_other_axis test/unit/test_residual_gain_other_axis.cpp)
piezo_unit_test(test_residual_preisach test/unit/test_residual_preisach.cpp)
piezo_unit_test(test_residual_mid_history test/unit/test_residual_mid_history.cpp)
piezo_unit_test(test_residual_two_effects test/unit/test_residual_two_effects.cpp)
piezo_unit_test(test_residual_steps test/unit/test_residual_steps.cpp)
piezo_unit_test(test_residual_sensitivity test/unit/test_residual_sensitivity.cpp)
piezo_unit_test(test_eval_stream test/unit/test_eval_stream.cpp)
# The clean reference figures several of the binaries above compare against, each a fit on 6 h of data: computed
# once per ctest run by a fixture instead of in every binary (a binary run by hand computes its own).
piezo_unit_test_shards(test_residual_refs test/unit/test_residual_refs.cpp SHARDS
                       sim_clean ResidualRefs.SimClean gain_base ResidualRefs.GainBase)
set(residual_refs ${CMAKE_BINARY_DIR}/test_results/refs)
piezo_reference_fixture(test_residual_refs_sim_clean PIEZO_REF_RESIDUAL_SIM_CLEAN
                        ${residual_refs}/residual_sim_clean.txt test_residual_sim test_residual_sim_coupling
                        test_residual_sim_periodic test_residual_sim_disturbance)
piezo_reference_fixture(test_residual_refs_gain_base PIEZO_REF_RESIDUAL_GAIN_BASE
                        ${residual_refs}/residual_gain_base.txt test_residual_gain_drift
                        test_residual_gain_other_axis test_residual_gain_temperature test_residual_two_effects)
if(TARGET test_residual_augmented)
  target_compile_definitions(test_residual_augmented PRIVATE PIEZO_C_COMPILER="${CMAKE_C_COMPILER}")
endif()
piezo_slow_tests(test_residual_loop test_residual_sim test_residual_sim_coupling test_residual_sim_periodic
                 test_residual_sim_disturbance test_residual_gain test_residual_gain_drift test_residual_preisach
                 test_residual_mid_history test_residual_loop_signals test_residual_loop_coupling
                 test_residual_sim_clean test_residual_gain_temperature test_residual_gain_other_axis
                 test_residual_two_effects test_residual_steps test_residual_sensitivity test_residual_refs_sim_clean
                 test_residual_refs_gain_base)

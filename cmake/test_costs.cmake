# The order CTest starts the slow tests in on a fresh build tree (it has no timing record there; later runs use
# the record). Longest first, so a run does not end on one long test alone: the figure is each test's time in
# seconds, measured alone on the 2-core machine (CPU for the computing tests, wall for the rostests and vcan_vm).
# Within a class (cpu or ros slot, piezo_test_budget) only the order matters. A name that no longer exists fails
# the configuration (piezo_ctest_name).
function(piezo_test_costs)
  if(NOT CATKIN_ENABLE_TESTING)
    return()
  endif()
  set(args ${ARGN})
  list(LENGTH args n)
  math(EXPR last "${n} - 1")
  foreach(i RANGE 0 ${last} 2)
    math(EXPR j "${i} + 1")
    list(GET args ${i} name)
    list(GET args ${j} seconds)
    piezo_ctest_name(test ${name})
    set_tests_properties(${test} PROPERTIES COST ${seconds})
  endforeach()
endfunction()

piezo_test_costs(
  # computing tests [s of CPU]; the reference fixtures first, as four tests each wait for one
  test_residual_refs_sim_clean 99  test_residual_refs_gain_base 98
  test_residual_two_effects 32  test_residual_sim 27  test_stage_matrix_mm3e_preisach_creep 31
  test_residual_gain_temperature 30  test_residual_sim_coupling 18  test_residual_sim_disturbance 25
  test_residual_sim_periodic 25  test_residual_sensitivity 12  test_sensor_reading_model 10  test_stage_matrix_mm3e_pi_creep 21  test_residual_gain_other_axis 25
  test_residual_gain_drift 25  test_stage_matrix_mm3e_preisach 21  test_stage_matrix_mm3e_pi 18
  test_stage_matrix_stack150_pi 17  test_stage_matrix_stack150_preisach 17  test_models_preisach_preisach 20
  test_stage_matrix_stack150_preisach_creep 16  test_residual_preisach 15  test_stage_matrix_stack150_pi_creep 16
  test_residual_sim_clean 13  test_stage_matrix_lowvolt_pi 7  test_stage_matrix_lowvolt_preisach 10
  test_stage_matrix_lowvolt_pi_creep 5  test_models_prony 11  test_hold_trim 11  test_residual_gain 10
  test_stage_matrix_lowvolt_preisach_creep 6
  # rostests and the VM [s of wall]
  vcan_vm 100  tracking_trim 53  live_loop 48  hold_trim_thermal 33  hold_trim 31  hold_trim_a 26  recorder_protocols 26  recorder_lockstep 26
  predictor_replay 23  sim_launch 12  sim_launch_broken_model 12  predictor_inputs 11)

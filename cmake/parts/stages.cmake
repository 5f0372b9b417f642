# Any-piezo checks (issue 11): noise floor from the data, model selection, sanity gates, the stage test matrix.
piezo_unit_test(test_analysis_noise_floor test/unit/test_analysis_noise_floor.cpp)
piezo_unit_test(test_analysis_model_selection test/unit/test_analysis_model_selection.cpp)
# The matrix as four CTest tests, one per physics, each over the three stages (CTest runs them in parallel).
piezo_unit_test_shards(test_stage_matrix test/unit/test_stage_matrix.cpp SHARDS
  pi "*/lowvolt_pi:*/stack150_pi:*/mm3e_pi" pi_creep "*/lowvolt_pi_creep:*/stack150_pi_creep:*/mm3e_pi_creep"
  preisach "*/lowvolt_preisach:*/stack150_preisach:*/mm3e_preisach"
  preisach_creep "*/lowvolt_preisach_creep:*/stack150_preisach_creep:*/mm3e_preisach_creep")
piezo_slow_tests(test_analysis_model_selection test_stage_matrix_pi test_stage_matrix_pi_creep test_stage_matrix_preisach
                 test_stage_matrix_preisach_creep)

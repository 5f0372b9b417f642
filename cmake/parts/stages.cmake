# Any-piezo checks: noise floor from the data, model selection, sanity gates, the stage test matrix.
piezo_unit_test(test_analysis_noise_floor test/unit/test_analysis_noise_floor.cpp)
piezo_unit_test(test_analysis_model_selection test/unit/test_analysis_model_selection.cpp)
piezo_unit_test(test_auto_stability test/unit/test_auto_stability.cpp)
# The matrix as one CTest test per stage (twelve), which CTest runs side by side: one process for the whole
# matrix would take minutes, and each shard stays within the per-test budget.
set(stage_shards)
set(stage_tests)
foreach(stage lowvolt stack150 mm3e)
  foreach(physics pi pi_creep preisach preisach_creep)
    list(APPEND stage_shards ${stage}_${physics} "*/${stage}_${physics}")
    list(APPEND stage_tests test_stage_matrix_${stage}_${physics})
  endforeach()
endforeach()
piezo_unit_test_shards(test_stage_matrix test/unit/test_stage_matrix.cpp SHARDS ${stage_shards})
piezo_slow_tests(test_analysis_model_selection test_auto_stability ${stage_tests})

# Any-piezo checks (issue 11): noise floor from the data, model selection, sanity gates, the stage test matrix.
piezo_unit_test(test_analysis_noise_floor test/unit/test_analysis_noise_floor.cpp)

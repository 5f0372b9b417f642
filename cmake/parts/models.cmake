# features/, models/ (linear, PI, creep, model file, C export), training/ (lasso, fit_common), analysis/ (eval).
piezo_unit_test(test_features_stream test/unit/test_features_stream.cpp)
piezo_unit_test(test_lasso test/unit/test_lasso.cpp)

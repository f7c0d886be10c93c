//! The Prophesee RAW container header (`% key value` lines) shared by EVT 2.0 and 3.0.

//! Text/CSV event files: any delimiter, optional header, configurable columns, time unit and polarity.

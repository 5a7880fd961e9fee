//! Every setting's default is its flag's (clap's), so each has one: a config struct's
//! `Default` is its flags parsed from an empty command line.

/// `T`'s flags parsed from an empty command line: every field at its flag's default.
pub fn defaults<T: clap::Args + clap::FromArgMatches>() -> T {
    let matches = T::augment_args(clap::Command::new("pbrl")).get_matches_from(["pbrl"]);
    // NOTE: an empty command line cannot fail to parse (every flag has a default or is
    // optional), nor can its matches fail to fill `T`.
    T::from_arg_matches(&matches).expect("the flags' defaults fill the struct")
}

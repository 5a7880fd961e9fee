//! The teachers: scripted (the six B-Pref teachers) and human. Built by the preference
//! learning issues; empty until then.

"""HTTP plumbing every route shares: JSON bodies (`json_body`), content types
(`content_types`), body limits (`limits`), connection deadlines (`connections`), request
metrics (`metrics`), HEAD (`head`), `?fields=` (`fields`), 4xx errors (`errors`,
`path_errors`), the log (`logs`), offline API docs (`api_docs`) and the dependency aliases with
the admin-token rule (`deps`)."""

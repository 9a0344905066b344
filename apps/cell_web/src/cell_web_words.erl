%% @doc Errors of the cell in words for the panel's answers, never as Erlang terms.
%%
%% The panel answers people and pages, who cannot read `{no_revision,machine,7}': the
%% reasons the panel knows get their own words here; {@link no_terms/1} is the last
%% guard every error message passes (in {@link cell_web_req:fail/4}): a binary written
%% as `<<"x">>' becomes `"x"', and a message still holding a term is replaced by
%% general words, the term going to the trace log for whoever looks into it.
-module(cell_web_words).

-export([settings_error/1, recipe_error/1, no_terms/1, has_terms/1]).

%% @doc An error of `cell_settings' (or of a schema's check) in words.
-spec settings_error(term()) -> binary().
settings_error({invalid, Path, Why} = E) ->
    case invalid_why(Why) of
        known -> no_terms(cell_settings_schema:format_error(E));
        Words -> iolist_to_binary([cell_settings_schema:format_path(Path), ": ", Words])
    end;
settings_error(not_json) ->
    <<"the text is not valid JSON">>;
settings_error({no_revision, Name, Rev}) ->
    iolist_to_binary(["there is no revision ", number(Rev), " of the ", name(Name), " settings"]);
settings_error({unknown_settings, Name}) ->
    iolist_to_binary(["there are no settings called ", name(Name)]);
settings_error({bad_who, _}) ->
    <<"the change does not say who made it">>;
settings_error({file, _Path, Reason}) ->
    iolist_to_binary(["the settings file cannot be written: ", file_reason(Reason)]);
settings_error(Other) ->
    unknown(Other).

invalid_why(no_admin) -> "at least one user must be an admin";
invalid_why({duplicate_user, Name}) when is_binary(Name) -> ["the user ", Name, " is given twice"];
invalid_why(bad_user_name) -> "a user name is 1 to 64 letters, digits and . _ - @";
invalid_why(_) -> known.

%% @doc An error of `cell_recipe' in words.
-spec recipe_error(term()) -> binary().
recipe_error(Why) ->
    no_terms(cell_recipe:format_error(Why)).

number(N) when is_integer(N), abs(N) < 1000000000000 -> integer_to_binary(N);
number(_) -> <<"asked for">>.

name(A) when is_atom(A) -> atom_to_binary(A, utf8);
name(B) when is_binary(B), byte_size(B) =< 64 -> B;
name(_) -> <<"of that name">>.

file_reason(R) when is_atom(R) -> file:format_error(R);
file_reason(_) -> "the disc refused it".

unknown(Term) ->
    cell_log:trace(web, "an error without words for the panel: ~0tP", [Term, 30]),
    <<"the cell refused this; the trace log says why">>.

%% @doc A message without Erlang terms: binaries written as terms become quoted
%% text; a message still holding a term is replaced by general words.
-spec no_terms(unicode:chardata()) -> binary().
no_terms(Message) ->
    Text = unicode:characters_to_binary(Message),
    Quoted = re:replace(Text, <<"<<\"((?:[^\"\\\\]|\\\\.)*)\">>">>, <<"\"\\1\"">>,
                        [global, unicode, {return, binary}]),
    case has_terms(Quoted) of
        false -> Quoted;
        true -> unknown(Text)
    end.

%% @doc Whether a text holds Erlang term syntax: a tuple opening with an atom
%% (`{name,'), a binary (`<<'), a map (`#{'), a pid, a reference or a fun. JSON never
%% does: its objects open with a quoted key.
-spec has_terms(binary()) -> boolean().
has_terms(Text) ->
    re:run(Text, <<"\\{(?:[a-z][A-Za-z0-9_@]*|'[^']*'),|<<|#\\{|<[0-9]+\\.[0-9]+\\.[0-9]+>|"
                   "#Ref<|#Fun<">>, [unicode]) =/= nomatch.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

settings_error_test_() ->
    [?_assertEqual(<<"there is no revision 7 of the machine settings">>,
                   settings_error({no_revision, machine, 7})),
     ?_assertEqual(<<"there is no revision asked for of the machine settings">>,
                   settings_error({no_revision, machine, 1000000000000000000000000000})),
     ?_assertEqual(<<"users: at least one user must be an admin">>,
                   settings_error({invalid, [users], no_admin})),
     ?_assertEqual(<<"users: the user op is given twice">>,
                   settings_error({invalid, [users], {duplicate_user, <<"op">>}})),
     ?_assertEqual(<<"speed: unknown field">>, settings_error({invalid, [speed], unknown_field})),
     ?_assertEqual(<<"there are no settings called robot">>,
                   settings_error({unknown_settings, robot})),
     ?_assertEqual(<<"the settings file cannot be written: no space left on device">>,
                   settings_error({file, "x", enospc})),
     ?_assertEqual(<<"the cell refused this; the trace log says why">>,
                   settings_error({something, new, 1}))].

no_terms_test_() ->
    [?_assertEqual(<<"\"a/b\" is not a usable recipe name">>,
                   no_terms(<<"<<\"a/b\">> is not a usable recipe name">>)),
     ?_assertEqual(<<"say \"x\\\"y\" here">>, no_terms(<<"say <<\"x\\\"y\">> here">>)),
     ?_assertEqual(<<"the cell refused this; the trace log says why">>,
                   no_terms(<<"not taken: {timeout,plc}">>)),
     ?_assertEqual(<<"speed: expected a number, got [1,2]">>,
                   no_terms(<<"speed: expected a number, got [1,2]">>))].

has_terms_test_() ->
    [?_assert(has_terms(<<"{no_revision,machine,7}">>)),
     ?_assert(has_terms(<<"{'EXIT',x}">>)),
     ?_assert(has_terms(<<"#{a => 1}">>)),
     ?_assert(has_terms(<<"<<\"x\">>">>)),
     ?_assert(has_terms(<<"from <0.123.0>">>)),
     ?_assertNot(has_terms(<<"{\"error\":\"not_found\",\"message\":\"no, not here\"}">>)),
     ?_assertNot(has_terms(<<"{\"a\":{\"b\":[1,2]}}">>)),
     ?_assertNot(has_terms(<<"wait 3 s, then try again">>))].
-endif.

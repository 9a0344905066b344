#!/usr/bin/env escript
%% -*- erlang -*-
%%! -noshell
-mode(compile).
%%
%% Debian's PropEr 1.2 calls erlang:get_stacktrace/0, which OTP 24 removed:
%% on OTP 25 a property that raises kills quickcheck with `undef` and the
%% counterexample is lost. This rebuilds the affected modules from their
%% debug_info, binding the stacktrace in each catch clause instead
%% (`catch C:R:Stk`), into OutDir/ebin. Usage: cure_proper.escript OutDir
main([OutDir]) ->
    Ebin = filename:join(OutDir, "ebin"),
    ok = filelib:ensure_dir(filename:join(Ebin, "x")),
    Mods = [proper, proper_statem, proper_typeserver],
    lists:foreach(fun(M) -> cure(M, Ebin) end, Mods);
main(_) ->
    io:format(standard_error, "usage: cure_proper.escript OutDir~n", []),
    halt(2).

cure(Mod, Ebin) ->
    Beam = code:which(Mod),
    {ok, {Mod, [{abstract_code, {raw_abstract_v1, Forms0}}]}} =
        beam_lib:chunks(Beam, [abstract_code]),
    {ok, {Mod, [{compile_info, Info}]}} = beam_lib:chunks(Beam, [compile_info]),
    Forms = [form(F) || F <- Forms0],
    Opts0 = proplists:get_value(options, Info, []),
    Opts = [binary, return_errors, debug_info
            | [O || O <- Opts0, keep_option(O)]],
    case compile:forms(Forms, Opts) of
        {ok, Mod, Bin} ->
            ok = file:write_file(filename:join(Ebin, atom_to_list(Mod) ++ ".beam"), Bin);
        {ok, Mod, Bin, _Warnings} ->
            ok = file:write_file(filename:join(Ebin, atom_to_list(Mod) ++ ".beam"), Bin);
        {error, Errors, _} ->
            io:format(standard_error, "cannot rebuild ~p: ~p~n", [Mod, Errors]),
            halt(1)
    end.

%% Options that name files of the original build machine are dropped.
keep_option({i, _}) -> false;
keep_option({outdir, _}) -> false;
keep_option({d, _}) -> true;
keep_option({d, _, _}) -> true;
keep_option(_) -> false.

form({function, L, N, A, Clauses}) ->
    {function, L, N, A, [walk(C) || C <- Clauses]};
form(F) -> F.

%% Bottom-up: inner trys are cured first, so each catch clause only sees the
%% get_stacktrace calls that belong to it.
walk({'try', L, Body, OfCls, CatchCls, After}) ->
    {'try', L, walk(Body), walk(OfCls), [catch_clause(walk(C)) || C <- CatchCls],
     walk(After)};
walk(T) when is_tuple(T) -> list_to_tuple(walk(tuple_to_list(T)));
walk(L) when is_list(L) -> [walk(E) || E <- L];
walk(X) -> X.

catch_clause({clause, L, [{tuple, TL, [Class, Reason, Stk0]}], Guard, Body} = C) ->
    case calls_get_stacktrace(Body) of
        false ->
            C;
        true ->
            Var = {var, TL, 'CuredStacktrace__'},
            {var, _, '_'} = Stk0,
            {clause, L, [{tuple, TL, [Class, Reason, Var]}], Guard, subst(Body, Var)}
    end;
catch_clause(C) -> C.

calls_get_stacktrace({call, _, {remote, _, {atom, _, erlang}, {atom, _, get_stacktrace}}, []}) ->
    true;
calls_get_stacktrace(T) when is_tuple(T) -> calls_get_stacktrace(tuple_to_list(T));
calls_get_stacktrace(L) when is_list(L) -> lists:any(fun calls_get_stacktrace/1, L);
calls_get_stacktrace(_) -> false.

subst({call, _, {remote, _, {atom, _, erlang}, {atom, _, get_stacktrace}}, []}, Var) -> Var;
subst(T, Var) when is_tuple(T) -> list_to_tuple(subst(tuple_to_list(T), Var));
subst(L, Var) when is_list(L) -> [subst(E, Var) || E <- L];
subst(X, _) -> X.

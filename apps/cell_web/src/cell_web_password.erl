%% @doc Password hashes of the panel's users: PBKDF2-HMAC-SHA256 with a random 16-byte
%% salt and an iteration count stored beside the hash, so the count can be raised for
%% new passwords without locking out the old ones. Pure: the process that serialises
%% the work is {@link cell_web_hasher}.
%%
%% 600,000 iterations is OWASP's figure for PBKDF2-HMAC-SHA256 (Password Storage Cheat
%% Sheet, 2023): about 0.2 s on a cell's PC. Comparisons take the same time whatever
%% the bytes (`crypto:hash_equals/2').
-module(cell_web_password).

-export([new/1, new/2, verify/2, check_new/1, default_iterations/0, demo/1]).

-export_type([hash/0]).

%% As stored in the users settings object (see cell_web_user).
-type hash() :: #{algorithm := pbkdf2_sha256, iterations := pos_integer(),
                  salt := binary(), hash := binary()}.

-define(ITERATIONS, 600000).
-define(SALT_BYTES, 16).
-define(HASH_BYTES, 32).
-define(MIN_CHARS, 8).
-define(MAX_BYTES, 1024).

%% @doc The iteration count for new passwords.
-spec default_iterations() -> pos_integer().
default_iterations() -> ?ITERATIONS.

%% @doc The stored form of a new password.
-spec new(binary()) -> hash().
new(Password) ->
    new(Password, ?ITERATIONS).

-spec new(binary(), pos_integer()) -> hash().
new(Password, Iterations) when is_binary(Password), is_integer(Iterations), Iterations > 0 ->
    Salt = crypto:strong_rand_bytes(?SALT_BYTES),
    #{algorithm => pbkdf2_sha256, iterations => Iterations, salt => base64:encode(Salt),
      hash => base64:encode(derive(Password, Salt, Iterations))}.

%% @doc Whether a password matches a stored hash. A malformed stored hash matches
%% nothing.
-spec verify(binary(), hash()) -> boolean().
verify(Password, #{algorithm := pbkdf2_sha256, iterations := N, salt := Salt64,
                   hash := Hash64}) when is_binary(Password), is_integer(N), N > 0 ->
    try {base64:decode(Salt64), base64:decode(Hash64)} of
        {Salt, Hash} when byte_size(Hash) =:= ?HASH_BYTES ->
            crypto:hash_equals(derive(Password, Salt, N), Hash);
        _ ->
            false
    catch
        error:_ -> false
    end;
verify(_, _) ->
    false.

%% @doc A new password must have at least 8 characters (NIST SP 800-63B) and at most
%% 1024 bytes (the hash input stays bounded).
-spec check_new(term()) -> ok | {error, too_short | too_long | not_text}.
check_new(P) when is_binary(P), byte_size(P) > ?MAX_BYTES -> {error, too_long};
check_new(P) when is_binary(P) ->
    case unicode:characters_to_list(P) of
        L when is_list(L), length(L) >= ?MIN_CHARS -> ok;
        L when is_list(L) -> {error, too_short};
        _ -> {error, not_text}
    end;
check_new(_) ->
    {error, not_text}.

%% @doc The demo accounts a new cell has: the password of each is its name. The salts
%% are fixed so the defaults of the users object stay the same from run to run.
-spec demo(operator | service | admin) -> hash().
demo(operator) ->
    stored(<<"IfOddW/2Mda6ieWXUskO9g==">>, <<"lvTi08VPoVeLT6uw2zuJ6WRJHN9ejo0g0qY4DObv2q0=">>);
demo(service) ->
    stored(<<"BHb7Q56a7bwt9UqrBIJ8IA==">>, <<"WxMdEvRDunYKRyL1YeU8s5XtXx5gQSSV1m8FjLLWtig=">>);
demo(admin) ->
    stored(<<"J2aFxGZaMZm4A5XOLpksfw==">>, <<"5L3qc/qLPqcoXOzXSekcNSnla/TrMLQbt+sMhl/QOMo=">>).

stored(Salt, Hash) ->
    #{algorithm => pbkdf2_sha256, iterations => ?ITERATIONS, salt => Salt, hash => Hash}.

derive(Password, Salt, Iterations) ->
    crypto:pbkdf2_hmac(sha256, Password, Salt, Iterations, ?HASH_BYTES).

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

%% RFC 7914 §11: PBKDF2-HMAC-SHA256 of "passwd" / "salt", one iteration, 64 bytes.
rfc7914_vector_test() ->
    Expected = <<16#55, 16#ac, 16#04, 16#6e, 16#56, 16#e3, 16#08, 16#9f,
                 16#ec, 16#16, 16#91, 16#c2, 16#25, 16#44, 16#b6, 16#05>>,
    <<First:16/binary, _/binary>> = crypto:pbkdf2_hmac(sha256, <<"passwd">>, <<"salt">>, 1, 64),
    ?assertEqual(Expected, First).

roundtrip_test() ->
    H = new(<<"correct horse">>, 1000),
    ?assert(verify(<<"correct horse">>, H)),
    ?assertNot(verify(<<"correct hors">>, H)),
    ?assertNot(verify(<<"correct horse ">>, H)),
    %% A new salt each time: the same password never gives the same hash.
    ?assertNotEqual(maps:get(hash, H), maps:get(hash, new(<<"correct horse">>, 1000))).

malformed_test_() ->
    H = new(<<"secret12">>, 1000),
    [?_assertNot(verify(<<"secret12">>, H#{salt := <<"***">>})),
     ?_assertNot(verify(<<"secret12">>, H#{hash := base64:encode(<<"short">>)})),
     ?_assertNot(verify(<<"secret12">>, H#{iterations := 0})),
     ?_assertNot(verify(<<"secret12">>, #{})),
     ?_assertNot(verify(secret, H))].

demo_test_() ->
    {timeout, 60,
     [?_assert(verify(atom_to_binary(N), demo(N))) || N <- [operator, service, admin]]}.

check_new_test_() ->
    [?_assertEqual({error, too_short}, check_new(<<"1234567">>)),
     ?_assertEqual(ok, check_new(<<"12345678">>)),
     %% Characters, not bytes: eight umlauts are sixteen bytes and enough.
     ?_assertEqual({error, too_short}, check_new(<<"äääää"/utf8>>)),
     ?_assertEqual(ok, check_new(<<"ääääääää"/utf8>>)),
     ?_assertEqual(ok, check_new(binary:copy(<<"a">>, 1024))),
     ?_assertEqual({error, too_long}, check_new(binary:copy(<<"a">>, 1025))),
     ?_assertEqual({error, not_text}, check_new(<<255, 254, 253, 252, 251, 250, 249, 248>>)),
     ?_assertEqual({error, not_text}, check_new(12345678))].
-endif.

"""Settings from the environment and the command line."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest
from llm_server import ChatServer
from test_llm import SECRET, make_requests

from jaxdmd.proposers.llm import (
    PAPER_TEMPERATURE,
    LLMConfig,
    LLMConfigError,
    LLMProposer,
    ReplayProposer,
    add_llm_arguments,
    proposer_from_args,
)


def parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="jaxdmd.run")
    add_llm_arguments(parser)
    return parser.parse_args(list(argv))


def test_from_env_reads_the_variables_and_overrides_win() -> None:
    env = {
        "JAXDMD_LLM_BASE_URL": "https://api.deepseek.com/v1",
        "JAXDMD_LLM_MODEL": "deepseek-chat",
        "OPENAI_API_KEY": SECRET,
    }
    config = LLMConfig.from_env(env)
    assert config.base_url == "https://api.deepseek.com/v1" and config.model == "deepseek-chat"
    assert config.api_key == SECRET and config.api_key_source == "OPENAI_API_KEY"
    assert config.temperature == PAPER_TEMPERATURE == 1.2
    assert config.chat_url == "https://api.deepseek.com/v1/chat/completions"
    assert SECRET not in repr(config) and SECRET not in str(config)

    env["JAXDMD_LLM_API_KEY"] = "sk-other-key"
    config = LLMConfig.from_env(env, model="deepseek-reasoner", temperature=0.5)
    assert config.api_key == "sk-other-key" and config.api_key_source == "JAXDMD_LLM_API_KEY"
    assert config.model == "deepseek-reasoner" and config.temperature == 0.5


def test_missing_or_bad_settings_say_what_to_do() -> None:
    with pytest.raises(LLMConfigError, match="JAXDMD_LLM_BASE_URL"):
        LLMConfig.from_env({})
    with pytest.raises(LLMConfigError, match="JAXDMD_LLM_MODEL"):
        LLMConfig.from_env({"JAXDMD_LLM_BASE_URL": "http://127.0.0.1:8000/v1"})
    with pytest.raises(LLMConfigError, match="http"):
        LLMConfig(base_url="127.0.0.1:8000", model="m")
    with pytest.raises(LLMConfigError, match="concurrency"):
        LLMConfig(base_url="http://h/v1", model="m", concurrency=0)
    with pytest.raises(LLMConfigError, match="cache_dir"):
        LLMConfig(base_url="http://h/v1", model="m", replay=True)


def test_chat_url_accepts_full_endpoint_and_keeps_credentials_out() -> None:
    config = LLMConfig(base_url="http://u:pw-123@h:8080/v1/chat/completions/", model="m")
    assert config.chat_url == "http://h:8080/v1/chat/completions"
    assert config.url_auth is not None
    assert "pw-123" not in repr(config)


def test_no_llm_options_means_the_offline_proposer() -> None:
    assert proposer_from_args(parse(), environ={}) is None
    assert proposer_from_args(argparse.Namespace(), environ={}) is None


def test_llm_options_build_a_live_proposer(tmp_path: Path) -> None:
    ns = parse(
        "--llm",
        "http://127.0.0.1:8000/v1",
        "--model",
        "qwen",
        "--api-key-env",
        "MY_KEY",
        "--temperature",
        "0.9",
        "--llm-timeout",
        "30",
        "--llm-concurrency",
        "2",
        "--cache",
        str(tmp_path),
    )
    proposer = proposer_from_args(ns, environ={"MY_KEY": SECRET})
    assert isinstance(proposer, LLMProposer)
    config = proposer.config
    assert (config.base_url, config.model, config.api_key) == (
        "http://127.0.0.1:8000/v1",
        "qwen",
        SECRET,
    )
    assert config.temperature == 0.9 and config.request_timeout == 30.0
    assert config.concurrency == 2 and config.cache_dir == str(tmp_path)
    assert config.api_key_source == "$MY_KEY"
    assert SECRET not in repr(proposer)


def test_environment_alone_selects_the_llm() -> None:
    env = {"JAXDMD_LLM_BASE_URL": "http://127.0.0.1:11434/v1", "JAXDMD_LLM_MODEL": "llama3"}
    proposer = proposer_from_args(parse(), environ=env)
    assert isinstance(proposer, LLMProposer)
    assert proposer.config.model == "llama3" and proposer.config.api_key is None


def test_inconsistent_options_are_errors(tmp_path: Path) -> None:
    with pytest.raises(LLMConfigError, match="MY_KEY"):
        proposer_from_args(
            parse("--llm", "http://h/v1", "--model", "m", "--api-key-env", "MY_KEY"), {}
        )
    with pytest.raises(LLMConfigError, match="JAXDMD_LLM_MODEL"):
        proposer_from_args(parse("--llm", "http://h/v1"), {})
    with pytest.raises(LLMConfigError, match="only one"):
        proposer_from_args(parse("--cache", str(tmp_path), "--replay", str(tmp_path)), {})
    with pytest.raises(LLMConfigError, match="--llm URL"):
        proposer_from_args(parse("--cache", str(tmp_path)), {})


def test_cache_then_replay_through_the_command_line(tmp_path: Path) -> None:
    requests = make_requests(n_requests=2, n_samples=2)
    with ChatServer() as server:
        live = proposer_from_args(
            parse("--llm", server.url, "--model", "toy", "--cache", str(tmp_path)), environ={}
        )
        assert live is not None
        recorded = live.propose(requests)
    replay = proposer_from_args(parse("--replay", str(tmp_path)), environ={})
    assert isinstance(replay, ReplayProposer)
    assert replay.propose(requests) == recorded
    replay = proposer_from_args(parse("--replay", str(tmp_path), "--model", "toy"), environ={})
    assert replay is not None and replay.propose(requests) == recorded

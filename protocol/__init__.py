"""ballbar.protocol"""
